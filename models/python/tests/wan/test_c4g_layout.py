"""C4G's refinement layout (c4g/wan/c4g_layout.py) and its fixture package (models/fixtures/wan-vace-tiny-c4g):
the positioned transformer graph and the one-frame encoder against diffusers' PyTorch modules, the reference
run's stages against the formulas the Rust pipeline implements (per-part control input, DiffSynth's Euler
schedule, guided steps, decoding the rendered part only), and the facts of WAN_VACE.md it encodes."""

import json
import os

import numpy as np
import pytest
import torch

from c4g.wan import c4g_layout, configs, export

from tests.common import REPO
from tests.wan.test_package import ONNX_ATOL, session

FIXTURE = REPO / "models/fixtures/wan-vace-tiny-c4g"
CFG = configs.TINY_C4G
INPUTS = ["latents", "timestep", "text_embeddings", "control", "control_scale", "positions"]


@pytest.fixture(scope="module")
def meta() -> dict:
    return json.loads((FIXTURE / "refiner.json").read_text())


@pytest.fixture(scope="module")
def models():
    return configs.build_transformer(CFG.transformer, 0), configs.build_vae(CFG.vae, 0)


@pytest.fixture(scope="module")
def sessions():
    names = ("transformer", "vae_encoder", "vae_decoder", "vae_frame_encoder")
    return {name: session(FIXTURE / f"{name}.onnx") for name in names}


@pytest.fixture(scope="module")
def refs() -> dict:
    return {name: dict(np.load(FIXTURE / "reference" / f"{name}.npz")) for name in ("pipeline_c4g", "transformer_positions", "vae_frame")}


def run_transformer(sessions, latents, timestep, text, control, scale, positions) -> np.ndarray:
    feeds = dict(zip(INPUTS, (latents, np.asarray(timestep, np.float32).reshape(1), text, control, scale, positions)))
    return sessions["transformer"].run(None, feeds)[0]


def test_manifest_declares_the_layout_and_its_graphs(meta, sessions):
    layout = meta["layout"]
    assert layout["kind"] == "c4g" and layout["keyframes"] == 3 and layout["keyframe_position_offset"] == 500
    assert layout["rope_positions"] == 1024
    assert layout["sampler"] == {"solver": "euler", "schedule": "diffsynth", "steps": 50, "shift": 5.0, "guidance_scale": 5.0}
    # 5 rendered frames → 2 latent frames, after 3 keyframe slots.
    assert meta["frames"] == 5 and meta["latent"]["frames"] == 5 and meta["tokens"] == 5 * 2 * 3
    for name, sess in sessions.items():
        sig = meta["graphs"][name]
        assert {i.name: i.shape for i in sess.get_inputs()} == sig["inputs"], name
        assert {o.name: o.shape for o in sess.get_outputs()} == sig["outputs"], name
    assert meta["graphs"]["vae_encoder"]["outputs"]["latents"] == [1, 16, 2, 4, 6]
    assert meta["graphs"]["vae_frame_encoder"]["outputs"]["latents"] == [1, 16, 1, 4, 6]
    types = {i.name: i.type for i in sessions["transformer"].get_inputs()}
    assert types["positions"] == "tensor(int64)"


def test_explicit_rope_at_default_positions_is_diffusers_rope(models):
    transformer = configs.build_transformer(CFG.transformer, 0)
    stock = transformer.rope
    wrapped = c4g_layout.ExplicitTimeRope(stock)
    x = torch.zeros(1, 16, 5, 4, 6)
    for a, b in zip(stock(x), wrapped(x)):
        assert torch.equal(a, b)
    wrapped.positions = torch.tensor([500, 502, 504, 0, 1])
    cos, _ = wrapped(x)
    cos_t = cos.reshape(5, 2 * 3, -1)[:, 0, : stock.t_dim]
    expected = stock.freqs_cos[:, : stock.t_dim][[500, 502, 504, 0, 1]]
    assert torch.equal(cos_t, expected)


def test_positioned_transformer_graph_matches_pytorch(sessions, refs):
    r = refs["transformer_positions"]
    np.testing.assert_array_equal(r["positions"], [500, 503, 509, 0, 1])
    got = run_transformer(sessions, r["latents"], r["timestep"], r["text_embeddings"], r["control"], r["control_scale"], r["positions"])
    np.testing.assert_allclose(got, r["velocity"], atol=ONNX_ATOL, rtol=0)
    # The positions are used: VACE's positions give another velocity.
    plain = run_transformer(sessions, r["latents"], r["timestep"], r["text_embeddings"], r["control"], r["control_scale"], np.arange(5))
    assert np.abs(plain - r["velocity"]).max() > 1e-2


def test_transformer_graph_reproduces_every_reference_call(sessions, refs):
    r = refs["pipeline_c4g"]
    scale = np.ones(len(CFG.transformer["vace_layers"]), np.float32)
    for i, t in enumerate(r["timesteps"]):
        for text, out in (("prompt_embeds", "step_velocity_cond"), ("negative_prompt_embeds", "step_velocity_uncond")):
            got = run_transformer(sessions, r["step_latents"][i], t, r[text], r["control"], scale, r["positions"])
            np.testing.assert_allclose(got, r[out][i], atol=ONNX_ATOL, rtol=0, err_msg=f"step {i} {out}")


def test_frame_encoder_graph_matches_pytorch(sessions, refs):
    r = refs["vae_frame"]
    got = sessions["vae_frame_encoder"].run(None, {"video": r["frame"]})[0]
    np.testing.assert_allclose(got, r["latents_mode"], atol=ONNX_ATOL, rtol=0)


def normalise(meta, mode):
    mean = np.asarray(meta["latent"]["mean"], np.float32).reshape(1, 16, 1, 1, 1)
    std = np.asarray(meta["latent"]["std"], np.float32).reshape(1, 16, 1, 1, 1)
    return (mode - mean) * (1 / std)


def test_control_is_per_part_encodings_keyframes_first(meta, refs, sessions):
    """What the Rust side computes: each keyframe through the one-frame encoder (reactive half: a black
    frame, since the keyframe mask is 0), the padded rendered chunk through the chunk encoder (inactive
    half: all zeros), and a mask of 0 on keyframe slots and 1 on rendered latents."""
    r = refs["pipeline_c4g"]
    k = CFG.keyframes

    def video(frames):
        return (np.transpose(frames, (3, 0, 1, 2))[None] * 2 - 1).astype(np.float32)

    frame_enc = lambda v: normalise(meta, sessions["vae_frame_encoder"].run(None, {"video": v})[0])  # noqa: E731
    chunk_enc = lambda v: normalise(meta, sessions["vae_encoder"].run(None, {"video": v})[0])  # noqa: E731
    padded = r["rendered_padded"]
    np.testing.assert_array_equal(padded[: len(r["rendered"])], r["rendered"])
    np.testing.assert_array_equal(padded[len(r["rendered"]) :], np.repeat(r["rendered"][-1:], len(padded) - len(r["rendered"]), 0))
    blank = frame_enc(np.zeros((1, 3, 1, CFG.height, CFG.width), np.float32))
    inactive = np.concatenate([frame_enc(video(r["keyframes"][i : i + 1])) for i in range(k)] + [chunk_enc(video(padded) * 0)], axis=2)
    reactive = np.concatenate([blank] * k + [chunk_enc(video(padded))], axis=2)
    np.testing.assert_allclose(r["control"][:, :16], inactive, atol=ONNX_ATOL, rtol=0)
    np.testing.assert_allclose(r["control"][:, 16:32], reactive, atol=ONNX_ATOL, rtol=0)
    mask = r["control"][:, 32:]
    assert mask.shape[1] == 64 and (mask[:, :, :k] == 0).all() and (mask[:, :, k:] == 1).all()


def test_positions_are_keyframe_indices_plus_500_then_latent_indices(refs):
    r = refs["pipeline_c4g"]
    np.testing.assert_array_equal(r["keyframe_indices"], [0, 2, 4])
    np.testing.assert_array_equal(r["positions"], [500, 502, 504, 0, 1])


def test_diffsynth_schedule_is_linspace_from_one_shifted():
    sigmas, timesteps = c4g_layout.diffsynth_schedule(4, 5.0)
    np.testing.assert_allclose(sigmas, [1.0, 0.9375, 5 / 6, 0.625, 0.0], rtol=1e-12)
    np.testing.assert_allclose(timesteps, [1000.0, 937.5, 5000 / 6, 625.0], rtol=1e-12)


def test_steps_are_guided_euler_steps(refs):
    r = refs["pipeline_c4g"]
    g = float(r["guidance_scale"])
    sigmas, timesteps = c4g_layout.diffsynth_schedule(int(r["steps"]), float(r["shift"]))
    np.testing.assert_allclose(r["sigmas"], sigmas, rtol=1e-7)
    np.testing.assert_allclose(r["timesteps"], timesteps, rtol=1e-7)
    x = r["noise"]
    for i in range(int(r["steps"])):
        np.testing.assert_allclose(r["step_latents"][i], x, atol=1e-5, rtol=0)
        v = r["step_velocity_uncond"][i] + g * (r["step_velocity_cond"][i] - r["step_velocity_uncond"][i])
        x = x + (r["sigmas"][i + 1] - r["sigmas"][i]) * v
    np.testing.assert_allclose(x, r["latents_final"], atol=1e-4, rtol=0)


def test_output_is_the_rendered_part_decoded_and_unpadded(meta, refs, sessions):
    r = refs["pipeline_c4g"]
    k, n = CFG.keyframes, len(r["rendered"])
    mean = np.asarray(meta["latent"]["mean"], np.float32).reshape(1, 16, 1, 1, 1)
    std = np.asarray(meta["latent"]["std"], np.float32).reshape(1, 16, 1, 1, 1)
    np.testing.assert_allclose(r["decoder_input"], r["latents_final"][:, :, k:] / (1 / std) + mean, atol=1e-5, rtol=0)
    video = sessions["vae_decoder"].run(None, {"latents": r["decoder_input"]})[0]
    frames = np.clip(np.transpose(video[0], (1, 2, 3, 0)) * 0.5 + 0.5, 0, 1)[:n]
    assert r["frames_out"].shape == (n, CFG.height, CFG.width, 3)
    np.testing.assert_allclose(frames, r["frames_out"], atol=ONNX_ATOL, rtol=0)


def test_fixture_inputs_are_reproducible(refs):
    inputs = c4g_layout.fixture_inputs(CFG, 3, rendered_frames=CFG.frames - 1)
    for key, value in inputs.items():
        np.testing.assert_array_equal(refs["pipeline_c4g"][key], value, err_msg=key)


def test_a_run_refuses_the_wrong_keyframe_count_and_too_many_rendered_frames(models):
    transformer, vae = models
    inputs = c4g_layout.fixture_inputs(CFG, 3, rendered_frames=2)
    with pytest.raises(ValueError, match="keyframes"):
        c4g_layout.run(transformer, vae, CFG, {**inputs, "keyframes": inputs["keyframes"][:2]}, 1, 5.0, 5.0)
    with pytest.raises(ValueError, match="rendered frames"):
        c4g_layout.pad_rendered(np.zeros((6, 2, 2, 3)), 5)


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("C4G_WAN_REGENERATE"), reason="slow: set C4G_WAN_REGENERATE=1")
def test_regenerated_fixture_matches_the_committed_one(tmp_path):
    export.export_tiny_c4g(tmp_path)
    for rel in ("refiner.json", "README.md", "reference/README.md"):
        assert (tmp_path / rel).read_text() == (FIXTURE / rel).read_text(), rel
    for npz in (FIXTURE / "reference").glob("*.npz"):
        new, old = np.load(tmp_path / "reference" / npz.name), np.load(npz)
        for key in old.files:
            np.testing.assert_allclose(new[key], old[key], atol=1e-5, rtol=0, err_msg=f"{npz.name}/{key}")


def test_layout_bench_counts_latent_frames_of_the_same_frames():
    from c4g.wan.bench import layouts as bench_layouts

    assert [bench_layouts.pad_to_chunk(n) for n in (1, 2, 5, 23, 35)] == [1, 5, 5, 25, 37]
    # C4G's training window: 12 keyframes and 23 rendered frames.
    got = bench_layouts.layouts(12, 23)
    assert got["vace"] == {"video_frames": 37, "latent_frames": 10, "keyframes": 0}
    assert got["c4g"] == {"video_frames": 25, "latent_frames": 19, "keyframes": 12}


def test_a_checkpoint_exports_in_the_c4g_layout(tmp_path, models):
    """The real-weights path (--diffusers --layout c4g) at another size: keyframe slots, the one-frame
    encoder, the public code's sampler defaults, and positions that reach the graph."""
    from c4g.wan import reference

    transformer, vae = models
    ckpt, out = tmp_path / "checkout", tmp_path / "package"
    transformer.save_pretrained(ckpt / "transformer")
    vae.save_pretrained(ckpt / "vae")
    reference.unipc(3.0).save_pretrained(ckpt / "scheduler")
    args = ["--diffusers", str(ckpt), "--layout", "c4g", "--keyframes", "2", "--frames", "5", "--height", "16", "--width", "32", "--text-tokens", "8"]
    assert export.main([*args, "--out", str(out)]) == 0
    meta = json.loads((out / "refiner.json").read_text())
    assert meta["layout"]["kind"] == "c4g" and meta["layout"]["keyframes"] == 2
    assert (meta["latent"]["frames"], meta["sampler"]["steps"], meta["sampler"]["shift"]) == (4, 50, 5.0)
    frame = session(out / "vae_frame_encoder.onnx").run(None, {"video": np.zeros((1, 3, 1, 16, 32), np.float32)})[0]
    assert frame.shape == (1, 16, 1, 2, 4)
    gen = torch.Generator().manual_seed(1)
    feeds = {
        "latents": torch.randn(1, 16, 4, 2, 4, generator=gen),
        "timestep": torch.tensor([500.0]),
        "text_embeddings": torch.randn(1, 8, 32, generator=gen),
        "control": torch.randn(1, 96, 4, 2, 4, generator=gen),
        "positions": c4g_layout.positions([0, 2], 2),
    }
    expected = c4g_layout.velocity(transformer, feeds["latents"], 500.0, feeds["text_embeddings"], feeds["control"], feeds["positions"]).numpy()
    got = session(out / "transformer.onnx").run(None, {**{k: v.numpy() for k, v in feeds.items()}, "control_scale": np.ones(2, np.float32)})[0]
    np.testing.assert_allclose(got, expected, atol=ONNX_ATOL, rtol=0)
