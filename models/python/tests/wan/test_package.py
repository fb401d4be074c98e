"""The Wan2.1-VACE refiner fixture (models/fixtures/wan-vace-tiny): its graphs against diffusers' PyTorch
modules, its manifest and weights against what the export writes, and its reference outputs against the
formulas the Rust pipeline implements (control tensor, latent normalisation, Euler steps with guidance)."""

import copy
import json
import os

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from c4g.wan import configs, export, onnx_graphs, reference, text

from tests.common import REPO

FIXTURE = REPO / "models/fixtures/wan-vace-tiny"
ONNX_ATOL = 1e-4  # f32 graph vs PyTorch; measured ~5e-7 (transformer, encoder) and ~1e-5 (decoder)
TRANSFORMER_INPUTS = ["latents", "timestep", "text_embeddings", "control", "control_scale"]
PIPELINES = ["pipeline_unipc", "pipeline_euler", "pipeline_unipc_lora"]


def session(path) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def meta() -> dict:
    return json.loads((FIXTURE / "refiner.json").read_text())


@pytest.fixture(scope="module")
def models():
    """The tiny models exactly as the export builds them (seed 0)."""
    return configs.build_transformer(configs.TINY.transformer, 0), configs.build_vae(configs.TINY.vae, 0)


@pytest.fixture(scope="module")
def sessions():
    return {name: session(FIXTURE / f"{name}.onnx") for name in ("transformer", "vae_encoder", "vae_decoder")}


@pytest.fixture(scope="module")
def refs() -> dict:
    return {name: dict(np.load(FIXTURE / "reference" / f"{name}.npz")) for name in (*PIPELINES, "transformer", "vae")}


def run_transformer(sessions, latents, timestep, text, control, scale) -> np.ndarray:
    feeds = dict(zip(TRANSFORMER_INPUTS, (latents, np.asarray(timestep, np.float32).reshape(1), text, control, scale)))
    return sessions["transformer"].run(None, feeds)[0]


# ----------------------------------------------------------------------------- manifest and weights


def test_refiner_json_is_what_the_export_writes(meta, models):
    transformer, vae = models
    counts = {
        "transformer": sum(p.numel() for p in transformer.parameters()),
        "vae": sum(p.numel() for p in vae.parameters()),
        "text_encoder": sum(p.numel() for p in text.build_text_encoder(text.UMT5_TINY, 6).parameters()),
    }
    expected = export.manifest(configs.TINY, meta["source"], "fused", "f32", counts, meta["files"]["lora"], text.UMT5_TINY, positions=False)
    expected["diffusers_config"] = {"transformer": export._config_dict(transformer), "vae": export._config_dict(vae)}
    assert json.loads(json.dumps(expected)) == meta


def test_graphs_have_the_documented_inputs_and_outputs(meta, sessions):
    for name, sess in sessions.items():
        sig = meta["graphs"][name]
        assert {i.name: i.shape for i in sess.get_inputs()} == sig["inputs"], name
        assert {o.name: o.shape for o in sess.get_outputs()} == sig["outputs"], name
        assert all(i.type == "tensor(float)" for i in (*sess.get_inputs(), *sess.get_outputs()))
    assert meta["graphs"]["transformer"]["inputs"]["control"] == [1, 96, 3, 4, 6]


def test_transformer_initializers_are_the_parameters_by_name_shape_and_value(models):
    proto = onnx.load(str(FIXTURE / "transformer.onnx"))
    assert proto.ir_version <= 13
    initializers = {t.name: onnx.numpy_helper.to_array(t) for t in proto.graph.initializer}
    params = dict(models[0].named_parameters())
    missing = [n for n in params if n not in initializers]
    assert not missing, missing
    for name, p in params.items():
        assert initializers[name].shape == tuple(p.shape), name
        np.testing.assert_array_equal(initializers[name], p.detach().numpy(), err_msg=name)
    assert "blocks.0.attn1.to_q.weight" in initializers
    assert initializers["blocks.0.attn1.to_q.weight"].shape == (32, 32)


def test_fixture_uses_fused_attention():
    ops = {n.op_type for n in onnx.load(str(FIXTURE / "transformer.onnx")).graph.node}
    assert "MultiHeadAttention" in ops and "Softmax" not in ops


# ----------------------------------------------------------------------------- the text side


def test_tokenizer_is_the_one_the_export_trains():
    committed = json.loads((FIXTURE / "tokenizer.json").read_text())
    assert json.loads(text.tiny_tokenizer().to_str()) == committed
    assert [committed["model"]["vocab"][i][0] for i in range(3)] == ["<pad>", "</s>", "<unk>"]


def test_text_encoder_graph_reproduces_the_pipelines_embeddings():
    """ONNX Runtime on the graph, fed the reference token ids, gives encode_prompt's embeddings on the
    real tokens (1e-5; measured ~7e-7); the reference's tokens are what the tokenizer gives today."""
    ref = json.loads((FIXTURE / "reference" / "text.json").read_text())
    embeddings = np.load(FIXTURE / "reference" / "text.npz")["embeddings"]
    tokenizer = text.fast_tokenizer(FIXTURE / "tokenizer.json")
    sess = session(FIXTURE / "text_encoder.onnx")
    assert {i.name: i.type for i in sess.get_inputs()} == {"input_ids": "tensor(int64)", "attention_mask": "tensor(int64)"}
    encoder = text.build_text_encoder(text.UMT5_TINY, 6)
    for case, expected in zip(ref["cases"], embeddings, strict=True):
        again = tokenizer([case["clean"]], padding="max_length", max_length=ref["tokens"], truncation=True)
        assert again["input_ids"][0] == case["input_ids"], case["caption"]
        ids = np.array([case["input_ids"]], np.int64)
        mask = np.array([case["attention_mask"]], np.int64)
        n = int(mask.sum())
        hidden = sess.run(None, {"input_ids": ids, "attention_mask": mask})[0][0]
        np.testing.assert_allclose(hidden[:n], expected[:n], atol=1e-5, rtol=0, err_msg=case["caption"])
        assert not expected[n:].any()
        with torch.no_grad():
            torch_hidden = encoder(input_ids=torch.from_numpy(ids), attention_mask=torch.from_numpy(mask)).last_hidden_state[0].numpy()
        np.testing.assert_allclose(torch_hidden[:n], expected[:n], atol=1e-6, rtol=0)


# ----------------------------------------------------------------------------- graphs vs PyTorch


def test_transformer_graph_matches_pytorch(sessions, refs, models):
    case = refs["transformer"]
    velocity = run_transformer(sessions, *(case[k] for k in TRANSFORMER_INPUTS))
    np.testing.assert_allclose(velocity, case["velocity"], atol=ONNX_ATOL, rtol=0)
    with torch.no_grad():
        again = models[0](
            hidden_states=torch.from_numpy(case["latents"]),
            timestep=torch.from_numpy(case["timestep"]),
            encoder_hidden_states=torch.from_numpy(case["text_embeddings"]),
            control_hidden_states=torch.from_numpy(case["control"]),
            control_hidden_states_scale=torch.from_numpy(case["control_scale"]),
            return_dict=False,
        )[0].numpy()
    np.testing.assert_allclose(again, case["velocity"], atol=1e-5, rtol=0)  # the reference is reproducible


@pytest.mark.parametrize("name", ["pipeline_unipc", "pipeline_euler"])
def test_transformer_graph_reproduces_every_pipeline_call(sessions, refs, name):
    r = refs[name]
    for i, t in enumerate(r["timesteps"]):
        for text, key in ((r["prompt_embeds"], "step_velocity_cond"), (r["negative_prompt_embeds"], "step_velocity_uncond")):
            v = run_transformer(sessions, r["step_latents"][i], t, text, r["control"], r["conditioning_scale"])
            np.testing.assert_allclose(v, r[key][i], atol=ONNX_ATOL, rtol=0, err_msg=f"{name} step {i} {key}")
    np.testing.assert_array_equal(r["velocity_first"], r["step_velocity_cond"][0])


def test_vae_graphs_match_pytorch(sessions, refs):
    case = refs["vae"]
    latents = sessions["vae_encoder"].run(None, {"video": case["video"]})[0]
    np.testing.assert_allclose(latents, case["latents_mode"], atol=ONNX_ATOL, rtol=0)
    video = sessions["vae_decoder"].run(None, {"latents": case["latents"]})[0]
    np.testing.assert_allclose(video, case["video_decoded"], atol=ONNX_ATOL, rtol=0)
    assert video.min() >= -1 and video.max() <= 1


@pytest.mark.slow
def test_diffusers_checkout_exports_a_package_with_plain_attention_and_external_data(tmp_path, models):
    """The real-weights path (--diffusers) on a diffusers-layout checkout of the tiny models, at another size."""
    transformer, vae = models
    ckpt, out = tmp_path / "checkout", tmp_path / "package"
    transformer.save_pretrained(ckpt / "transformer")
    vae.save_pretrained(ckpt / "vae")
    reference.unipc(3.0).save_pretrained(ckpt / "scheduler")
    encoder = text.build_text_encoder(text.UMT5_TINY, 6)
    encoder.save_pretrained(ckpt / "text_encoder")
    text.fast_tokenizer(FIXTURE / "tokenizer.json").save_pretrained(ckpt / "tokenizer")
    args = ["--diffusers", str(ckpt), "--frames", "5", "--height", "16", "--width", "32", "--text-tokens", "8", "--text-encoder"]
    assert export.main([*args, "--attention", "plain", "--external-data", "--out", str(out)]) == 0
    meta = json.loads((out / "refiner.json").read_text())
    assert meta["source"] == {"kind": "checkpoint", "path": str(ckpt)} and meta["attention"] == "plain"
    assert (meta["latent"]["frames"], meta["latent"]["height"], meta["latent"]["width"], meta["tokens"]) == (2, 2, 4, 4)
    assert meta["sampler"]["scheduler"]["class"] == "UniPCMultistepScheduler" and meta["sampler"]["shift"] == 3.0
    assert (out / "transformer.onnx.data").exists()
    proto = onnx.load(str(out / "transformer.onnx"), load_external_data=False)
    assert {n.op_type for n in proto.graph.node} >= {"Softmax"} and "MultiHeadAttention" not in {n.op_type for n in proto.graph.node}
    assert {n for n, _ in transformer.named_parameters()} <= {t.name for t in proto.graph.initializer}

    gen = torch.Generator().manual_seed(7)
    feeds = {
        "latents": torch.randn(1, 16, 2, 2, 4, generator=gen),
        "timestep": torch.tensor([625.0]),
        "text_embeddings": torch.randn(1, 8, 32, generator=gen),
        "control": torch.randn(1, 96, 2, 2, 4, generator=gen),
        "control_scale": torch.tensor([0.3, 1.2]),
    }
    assert meta["layout"] == {"kind": "vace"} and meta["graphs"]["transformer"]["inputs"]["positions"] == [2]
    with torch.no_grad():
        expected = transformer(
            hidden_states=feeds["latents"], timestep=feeds["timestep"], encoder_hidden_states=feeds["text_embeddings"],
            control_hidden_states=feeds["control"], control_hidden_states_scale=feeds["control_scale"], return_dict=False,
        )[0].numpy()  # fmt: skip
        video = torch.rand(1, 3, 5, 16, 32, generator=gen) * 2 - 1
        mode = vae.encode(video).latent_dist.mode().numpy()
    # New exports take temporal positions: VACE's layout feeds 0..F'-1, which is diffusers' own RoPE.
    velocity = session(out / "transformer.onnx").run(None, {**{k: v.numpy() for k, v in feeds.items()}, "positions": np.arange(2)})[0]
    np.testing.assert_allclose(velocity, expected, atol=ONNX_ATOL, rtol=0)
    latents = session(out / "vae_encoder.onnx").run(None, {"video": video.numpy()})[0]
    np.testing.assert_allclose(latents, mode, atol=ONNX_ATOL, rtol=0)

    # The text side: the checkout's tokenizer, and its encoder at the package's 8 tokens.
    assert meta["files"]["text_encoder"] == "text_encoder.onnx" and meta["graphs"]["text_encoder"]["outputs"]["last_hidden_state"] == [1, 8, 32]
    assert json.loads((out / "tokenizer.json").read_text())["model"] == json.loads((FIXTURE / "tokenizer.json").read_text())["model"]
    ids = torch.tensor([[5, 17, 40, 1, 0, 0, 0, 0]])
    mask = (torch.arange(8) < 4).long()[None]
    with torch.no_grad():
        hidden = encoder(input_ids=ids, attention_mask=mask).last_hidden_state.numpy()
    got = session(out / "text_encoder.onnx").run(None, {"input_ids": ids.numpy(), "attention_mask": mask.numpy()})[0]
    np.testing.assert_allclose(got, hidden, atol=ONNX_ATOL, rtol=0)


def test_fp16_transformer_keeps_f32_inputs_and_outputs(tmp_path, models, refs):
    path = tmp_path / "transformer.onnx"
    onnx_graphs.export_transformer(export.to_fp16(copy.deepcopy(models[0])), configs.TINY, path, fused=True)
    sess = session(path)
    types = {i.name: i.type for i in (*sess.get_inputs(), *sess.get_outputs())}
    assert types.pop("positions") == "tensor(int64)" and set(types.values()) == {"tensor(float)"}
    case = refs["transformer"]
    velocity = sess.run(None, {**{k: case[k] for k in TRANSFORMER_INPUTS}, "positions": np.arange(3)})[0]
    np.testing.assert_allclose(velocity, case["velocity"], atol=2e-2, rtol=0)  # measured ~2e-3


# ----------------------------------------------------------------------------- the pipeline's formulas


def mask_channels(mask: np.ndarray, latent_frames: int) -> np.ndarray:
    """[F, H, W] → [64, F', H/8, W/8]: 8 x 8 pixel-unshuffle (channel = dy * 8 + dx), nearest-exact in time."""
    f, h, w = mask.shape
    blocks = mask.reshape(f, h // 8, 8, w // 8, 8).transpose(2, 4, 0, 1, 3).reshape(64, f, h // 8, w // 8)
    source = np.floor((np.arange(latent_frames) + 0.5) * f / latent_frames).astype(int)
    return blocks[:, source]


def test_nearest_exact_picks_the_documented_frames():
    frames = np.arange(81, dtype=np.float32)[:, None, None] * np.ones((81, 8, 8), np.float32)
    picked = mask_channels(frames, 21)[0, :, 0, 0].astype(int).tolist()
    assert picked == [1, 5, 9, 13, 17, 21, 25, 28, 32, 36, 40, 44, 48, 52, 55, 59, 63, 67, 71, 75, 79]
    t = torch.from_numpy(frames)[None, None]
    torch_pick = torch.nn.functional.interpolate(t, size=(21, 8, 8), mode="nearest-exact")[0, 0, :, 0, 0]
    assert torch_pick.int().tolist() == picked


@pytest.mark.parametrize("name", PIPELINES)
def test_control_tensor_is_normalised_latents_and_unshuffled_mask(meta, refs, sessions, name):
    r = refs[name]
    mean = np.asarray(meta["latent"]["mean"], np.float32).reshape(1, 16, 1, 1, 1)
    inv_std = 1.0 / np.asarray(meta["latent"]["std"], np.float32).reshape(1, 16, 1, 1, 1)
    video = r["video"].transpose(3, 0, 1, 2)[None] * 2 - 1
    m = (r["mask"] > 0.5).astype(np.float32)[None, None]
    inactive = sessions["vae_encoder"].run(None, {"video": (video * (1 - m)).astype(np.float32)})[0]
    reactive = sessions["vae_encoder"].run(None, {"video": (video * m).astype(np.float32)})[0]
    np.testing.assert_allclose(inactive, r["inactive_latents_raw"], atol=ONNX_ATOL, rtol=0)
    np.testing.assert_allclose(reactive, r["reactive_latents_raw"], atol=ONNX_ATOL, rtol=0)
    control = np.concatenate(
        [(inactive - mean) * inv_std, (reactive - mean) * inv_std, mask_channels(r["mask"], meta["latent"]["frames"])[None]], axis=1
    )
    np.testing.assert_allclose(control, r["control"], atol=ONNX_ATOL, rtol=0)
    np.testing.assert_array_equal(control[:, 32:], r["control"][:, 32:])
    assert len({tuple(c) for c in r["control"][0, 32:, 1].reshape(64, -1)}) > 2  # the mask box cuts 8 x 8 blocks


@pytest.mark.parametrize("name", PIPELINES)
def test_decoded_frames_are_denormalised_latents_through_the_decoder(meta, refs, sessions, name):
    r = refs[name]
    mean = np.asarray(meta["latent"]["mean"], np.float32).reshape(1, 16, 1, 1, 1)
    inv_std = 1.0 / np.asarray(meta["latent"]["std"], np.float32).reshape(1, 16, 1, 1, 1)
    np.testing.assert_allclose(r["latents_final"] / inv_std + mean, r["decoder_input"], atol=1e-5, rtol=0)
    video = sessions["vae_decoder"].run(None, {"latents": r["decoder_input"]})[0]
    frames = np.clip(video / 2 + 0.5, 0, 1)[0].transpose(1, 2, 3, 0)
    np.testing.assert_allclose(frames, r["frames_out"], atol=ONNX_ATOL, rtol=0)


def test_euler_pipeline_steps_are_guided_euler_steps(refs):
    r = refs["pipeline_euler"]
    g = float(r["guidance_scale"])
    x = r["noise"]
    for i in range(int(r["steps"])):
        np.testing.assert_allclose(r["step_latents"][i], x, atol=1e-5, rtol=0)
        v = r["step_velocity_uncond"][i] + g * (r["step_velocity_cond"][i] - r["step_velocity_uncond"][i])
        x = x + (r["sigmas"][i + 1] - r["sigmas"][i]) * v
    np.testing.assert_allclose(x, r["latents_final"], atol=1e-4, rtol=0)
    np.testing.assert_allclose(r["timesteps"], r["sigmas"][:-1] * 1000, rtol=1e-6)


def test_unipc_timesteps_are_floored_shifted_sigmas(refs):
    r = refs["pipeline_unipc"]
    np.testing.assert_array_equal(r["timesteps"], [999, 937, 833, 625])
    np.testing.assert_allclose(r["sigmas"], [0.999999, 0.9375781, 0.833611, 0.6259361, 0.0], atol=1e-6)


def test_lora_changes_the_result_visibly(refs):
    base, lora = refs["pipeline_unipc"], refs["pipeline_unipc_lora"]
    np.testing.assert_array_equal(base["control"], lora["control"])
    assert np.abs(base["velocity_first"] - lora["velocity_first"]).max() > 0.1
    assert np.abs(base["frames_out"] - lora["frames_out"]).max() > 0.05


def test_sampler_json_is_diffusers_schedules():
    committed = json.loads((FIXTURE / "reference" / "sampler.json").read_text())
    assert json.loads(json.dumps(reference.sampler_reference())) == committed
    unipc = committed["cases"][0]["unipc"]
    assert committed["cases"][0]["steps"] == 4 and unipc["timesteps"] == [999, 937, 833, 625]


def test_reference_files_have_the_documented_keys_and_shapes(refs):
    lat = (1, 16, 3, 4, 6)
    shapes = {
        "video": (9, 32, 48, 3), "mask": (9, 32, 48), "prompt_embeds": (1, 16, 32), "negative_prompt_embeds": (1, 16, 32),
        "noise": lat, "inactive_latents_raw": lat, "reactive_latents_raw": lat, "control": (1, 96, 3, 4, 6),
        "sigmas": (5,), "timesteps": (4,), "velocity_first": lat, "step_latents": (4, *lat), "step_velocity_cond": (4, *lat),
        "step_velocity_uncond": (4, *lat), "latents_final": lat, "decoder_input": lat, "frames_out": (9, 32, 48, 3),
        "guidance_scale": (), "conditioning_scale": (2,), "shift": (), "steps": (),
    }  # fmt: skip
    for name in PIPELINES:
        assert {k: v.shape for k, v in refs[name].items()} == shapes, name
        assert all(v.dtype == np.float32 for k, v in refs[name].items() if k != "steps")
    assert {k: v.shape for k, v in refs["transformer"].items()} == {
        "latents": lat, "timestep": (1,), "text_embeddings": (1, 16, 32), "control": (1, 96, 3, 4, 6), "control_scale": (2,), "velocity": lat,
    }  # fmt: skip
    assert {k: v.shape for k, v in refs["vae"].items()} == {
        "video": (1, 3, 9, 32, 48), "latents_mode": lat, "latents": lat, "video_decoded": (1, 3, 9, 32, 48),
    }  # fmt: skip


def test_fixture_inputs_are_reproducible(refs):
    inputs = reference.fixture_inputs(configs.TINY, 3)
    for name in PIPELINES:
        for key, value in inputs.items():
            np.testing.assert_array_equal(refs[name][key], value, err_msg=f"{name}/{key}")


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("C4G_WAN_REGENERATE"), reason="slow (~1 min): set C4G_WAN_REGENERATE=1")
def test_regenerated_fixture_matches_the_committed_one(tmp_path):
    export.export_tiny(tmp_path)
    assert (tmp_path / "refiner.json").read_text() == (FIXTURE / "refiner.json").read_text()
    for rel in ("lora/name_map.json", "lora/peft/adapter_config.json", "reference/sampler.json", "README.md", "reference/README.md"):
        assert (tmp_path / rel).read_text() == (FIXTURE / rel).read_text(), rel
    for npz in (FIXTURE / "reference").glob("*.npz"):
        new, old = np.load(tmp_path / "reference" / npz.name), np.load(npz)
        assert set(new.files) == set(old.files)
        for key in old.files:
            np.testing.assert_allclose(new[key], old[key], atol=1e-5, rtol=0, err_msg=f"{npz.name}/{key}")


# ----------------------------------------------------------------------------- the real size


def test_1_3b_config_builds_the_real_architecture():
    counts = configs.transformer_parameter_count(configs.TRANSFORMER_1_3B)
    assert configs.parameter_count(configs.TRANSFORMER_1_3B) == counts["total"]
    assert 1.40e9 < counts["base"] < 1.44e9 and 0.72e9 < counts["vace"] < 0.75e9  # ~1.42B + ~0.73B
    assert configs.parameter_count(configs.TRANSFORMER_TINY) == configs.transformer_parameter_count(configs.TRANSFORMER_TINY)["total"]
    cfg = configs.WAN_1_3B
    cfg.validate()
    assert (cfg.latent_frames, cfg.latent_height, cfg.latent_width, cfg.tokens) == (21, 60, 104, 32760)
    sig = export.graph_signatures(cfg)["transformer"]["inputs"]
    assert sig["control_scale"] == [15] and sig["text_embeddings"] == [1, 512, 4096]


def test_tiny_rope_split_matches_the_head_dim():
    rope = configs.build_transformer(configs.TRANSFORMER_TINY, device="meta").rope
    assert (rope.t_dim, rope.h_dim, rope.w_dim) == (8, 4, 4)
    real = configs.build_transformer(configs.TRANSFORMER_1_3B, device="meta").rope
    assert (real.t_dim, real.h_dim, real.w_dim) == (44, 42, 42)
