"""The feature stream in the package: `feature_decoder.onnx` (the joint two-stream decoder) and its
declaration in model.json.

ONNX Runtime's float32 output is held to the mirror run in float64 (an independent precision: the
graph's rounding is all there is between them) within 1e-4 absolute, the project's mirror/engine
parity tolerance. Why that is enough room: float32 rounds at ~6e-8 relative per operation; two
pre-norm layers, softmax over ~50 tokens and LayerNorms that divide by a standard deviation of order
1 keep the accumulated error of these order-1 outputs near 1e-6 (measured: 5e-7 to 7e-7 at T = 1,
4 and 8), so 1e-4 fails only a graph that computes something else.
"""

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch
from safetensors.numpy import load_file

from c4g.model.config import C4GConfig
from c4g.model.init import random_init
from c4g.model.network import C4G
from c4g.model.time_policy import normalise_batch
from c4g.package.export import FEATURE_KINDS, export_package
from c4g.package.fixture import FEATURE_STREAM_CONFIG, FEATURE_STREAM_SEED

from tests.common import MODELS

CFG = C4GConfig(
    dino_dim=16, dino_depth=1, dino_heads=2, patch=7, pos_embed_grid=4,
    aggregator_dim=16, aggregator_depth=1, aggregator_heads=2,
    decoder_dim=32, decoder_heads=2, decoder_head_dim=16, decoder_mlp=64, decoder_depth=2,
    queries=24, time_dim=16, image_size=28, feature_dim=5,
)  # fmt: skip
TOL = 1e-4


def seeded(cfg: C4GConfig = CFG, seed: int = 9) -> C4G:
    m = C4G(cfg)
    random_init(m, seed)
    return m.eval()


@pytest.fixture(scope="module", params=["plain", "precomputed"])
def package(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param)
    manifest = export_package(seeded(), out, "features", "0.1.0", {"kind": "random-init", "seed": 9}, decoder_form=request.param, feature_kind="object-id")
    return out, manifest


def session(path):
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def test_model_json_declares_the_feature_decoder_its_width_and_kind(package):
    out, manifest = package
    on_disk = json.loads((out / "model.json").read_text())
    assert on_disk == manifest
    assert on_disk["files"]["feature_decoder"] == "feature_decoder.onnx"
    assert on_disk["feature_decoder"] == {"feature_width": 5, "kind": "object-id"}
    assert on_disk["architecture"]["feature_dim"] == 5


def test_the_feature_decoder_graph_takes_the_features_and_maps_in_either_decoder_form(package):
    out, _ = package
    s = session(out / "feature_decoder.onnx")
    assert [i.name for i in s.get_inputs()] == ["features", "context_times", "target_times", "context_feature_maps"]
    assert [o.name for o in s.get_outputs()] == ["gaussians", "gaussian_features"]


@pytest.mark.parametrize("frames,targets", [(1, 1), (4, 3)])
def test_onnx_runtime_lifts_the_features_the_float64_mirror_does(package, frames, targets):
    out, _ = package
    rng = np.random.default_rng(frames * 7 + targets)
    features = rng.standard_normal((frames, CFG.tokens_per_frame, CFG.feature_width)).astype(np.float32)
    maps = rng.standard_normal((frames, CFG.tokens_per_frame, CFG.feature_dim)).astype(np.float32)
    ctx = np.sort(rng.uniform(0, 1, (targets, frames)), axis=1).astype(np.float32)
    tgt = rng.uniform(0, 1, targets).astype(np.float32)
    exact = seeded().double()
    with torch.no_grad():
        as_f64 = [torch.from_numpy(a).double() for a in (features, ctx, tgt, maps)]
        want_gaussians, want = (t.numpy() for t in exact.decode_with_features(*as_f64))
    feed = {"features": features, "context_times": ctx, "target_times": tgt, "context_feature_maps": maps}
    gaussians, lifted = session(out / "feature_decoder.onnx").run(["gaussians", "gaussian_features"], feed)
    assert lifted.shape == (targets, CFG.queries, CFG.feature_dim)
    assert np.abs(want).max() > 0.1
    np.testing.assert_allclose(lifted, want, atol=TOL, rtol=0)
    np.testing.assert_allclose(gaussians, want_gaussians, atol=TOL, rtol=1e-3)  # scales are small: relative too


def test_a_package_without_a_stream_has_no_feature_decoder(tmp_path):
    (tmp_path / "feature_decoder.onnx").write_bytes(b"stale")  # from an earlier export into the folder
    manifest = export_package(seeded(C4GConfig.from_dict({**CFG.to_dict(), "feature_dim": 0})), tmp_path, "plain", "0.1.0", {"kind": "random-init"}, decoder_form="plain")
    assert "feature_decoder" not in manifest and "feature_decoder" not in manifest["files"]
    assert not (tmp_path / "feature_decoder.onnx").exists()


def test_the_kind_comes_from_the_recipe_and_an_encoder_stream_must_be_as_wide_as_the_features(tmp_path):
    manifest = export_package(seeded(), tmp_path / "a", "a", "0.1.0", {}, decoder_form="plain", training={"features": "object-id"})
    assert manifest["feature_decoder"]["kind"] == "object-id"
    manifest = export_package(seeded(), tmp_path / "b", "b", "0.1.0", {}, decoder_form="plain")
    assert "kind" not in manifest["feature_decoder"]  # random weights lift nothing in particular
    assert set(FEATURE_KINDS) == {"encoder", "object-id"}
    with pytest.raises(ValueError, match="encoder's 32-wide features"):
        export_package(seeded(), tmp_path / "c", "c", "0.1.0", {}, decoder_form="plain", feature_kind="encoder")


# -- the committed fixtures ----------------------------------------------------------------------------
FIXTURES = MODELS / "fixtures"


def fixture_cases(folder: Path):
    """(case, normalised context times, target times, reference tensors) of a fixture's reference.json."""
    ref = load_file(str(folder / "reference.safetensors"))
    for case in json.loads((folder / "reference.json").read_text())["cases"]:
        ctx, tgt = normalise_batch(case["times"], case["targets"], case["policy"])
        yield case, ctx, tgt, ref


@pytest.mark.parametrize(
    "package,maps_of",
    [
        ("feature-stream", lambda ref, name, t: ref[f"{name}/features"]),  # kind "encoder": the maps are the features
        ("decoder-forms/plain", lambda ref, name, t: ref["feature_maps"][:t]),
        ("decoder-forms/precomputed", lambda ref, name, t: ref["feature_maps"][:t]),
        ("c4g-small", lambda ref, name, t: ref["feature_maps"][:t]),
    ],
)
def test_the_committed_feature_decoders_reproduce_their_references(package, maps_of):
    """What the engine's tests hold it to: each committed feature_decoder.onnx, fed its reference's
    inputs, gives the reference's per-Gaussian features and Gaussians (c4g-small stores the features
    of its small cases only)."""
    folder = FIXTURES / package
    root = folder if (folder / "reference.json").exists() else folder.parent
    s = session(folder / "feature_decoder.onnx")
    checked = 0
    for case, ctx, tgt, ref in fixture_cases(root):
        name, t = case["case"], case["frames"]
        if f"{name}/features" not in ref:
            continue
        feed = {"features": ref[f"{name}/features"], "context_times": ctx, "target_times": tgt, "context_feature_maps": maps_of(ref, name, t)}
        gaussians, lifted = s.run(["gaussians", "gaussian_features"], feed)
        np.testing.assert_allclose(lifted, ref[f"{name}/gaussian_features"], atol=TOL, rtol=0, err_msg=name)
        np.testing.assert_allclose(gaussians, ref[f"{name}/gaussians"], atol=TOL, rtol=1e-3, err_msg=name)
        checked += 1
    assert checked >= 2


def test_the_feature_stream_fixture_declares_its_kind_and_is_the_mirror_s():
    folder = FIXTURES / "feature-stream"
    manifest = json.loads((folder / "model.json").read_text())
    assert manifest["feature_decoder"] == {"feature_width": FEATURE_STREAM_CONFIG.feature_width, "kind": "encoder"}
    assert manifest["files"]["feature_decoder"] == "feature_decoder.onnx"
    model = seeded(FEATURE_STREAM_CONFIG, FEATURE_STREAM_SEED)
    for case, ctx, tgt, ref in fixture_cases(folder):
        name, t = case["case"], case["frames"]
        with torch.no_grad():
            features = model.encode(torch.from_numpy(ref["frames"][:t]))
            gaussians, lifted = model.decode_with_features(features, torch.from_numpy(ctx), torch.from_numpy(tgt), features)
        # The same code on another machine's float32 kernels: rounding apart, nothing else.
        np.testing.assert_allclose(features.numpy(), ref[f"{name}/features"], atol=1e-5, rtol=0)
        np.testing.assert_allclose(lifted.numpy(), ref[f"{name}/gaussian_features"], atol=1e-5, rtol=0)
        np.testing.assert_allclose(gaussians.numpy(), ref[f"{name}/gaussians"], atol=1e-5, rtol=1e-4)
