"""The export tool: the ONNX graphs ONNX Runtime runs equal the PyTorch mirror and the reference, with
dynamic T and B, IR version <= 13, and the canonical layout computed inside the graph."""

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from c4g.model.time_policy import normalise_batch
from c4g.package import export

from tests.common import reference_cases, xyzw_to_wxyz


@pytest.fixture(scope="module")
def package(tmp_path_factory, official_small_dir):
    out = tmp_path_factory.mktemp("pkg") / "c4g-small"
    rc = export.main(
        ["--checkpoint", str(official_small_dir / "c4g_official_small.ckpt"), "--config", "official-small",
         "--feature-dim", "8", "--out", str(out)]
    )  # fmt: skip
    assert rc == 0
    return out


def session(path):
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def test_manifest_declares_what_the_package_holds(package):
    manifest = json.loads((package / "model.json").read_text())
    assert manifest["files"] == {"encoder": "encoder.onnx", "decoder": "decoder.onnx", "feature_decoder": "feature_decoder.onnx"}
    assert manifest["gaussian_count"] == 256 and manifest["tokens_per_frame"] == 256 and manifest["feature_width"] == 128
    assert manifest["feature_decoder"] == {"feature_width": 8}
    assert len(manifest["provenance"]["sha256"]) == 64
    assert manifest["rasterizer"] == {"footprint": "3dgs"}  # official layout, no training recipe
    for name in manifest["files"].values():
        model = onnx.load(str(package / name))
        assert model.ir_version <= 13


def test_the_declared_footprint_is_the_recipe_s_else_ellipse_for_our_models_and_3dgs_for_official_ones():
    assert export.declared_footprint(None) == "3dgs"
    assert export.declared_footprint({"steps": 2400}) == "ellipse"
    assert export.declared_footprint({"footprint": "3dgs"}) == "3dgs"
    with pytest.raises(ValueError, match="footprint"):
        export.declared_footprint({"footprint": "gsplat"})


def test_onnx_graphs_reproduce_reference(package, official_reference):
    enc, dec = session(package / "encoder.onnx"), session(package / "decoder.onnx")
    for case, index, targets in reference_cases(official_reference):
        frames = official_reference[f"{case}/frames"]
        (features,) = enc.run(None, {"frames": (frames - 0.5) / 0.5})
        np.testing.assert_allclose(features, official_reference[f"{case}/features"], atol=1e-4, rtol=0)
        ctx, tgt = normalise_batch(index, targets, policy="reference")
        (gaussians,) = dec.run(None, {"features": features, "context_times": ctx, "target_times": tgt})
        assert gaussians.shape == (len(targets), 256, 14)
        for b, target in enumerate(targets):
            p, g = f"{case}/t{int(target)}/", gaussians[b]
            np.testing.assert_allclose(g[:, 0:3], official_reference[p + "means"], atol=1e-4, rtol=0)
            np.testing.assert_allclose(g[:, 3:6], official_reference[p + "scales"], rtol=1e-3, atol=0)
            np.testing.assert_allclose(g[:, 6:10], xyzw_to_wxyz(official_reference[p + "rotations_xyzw"]), atol=1e-4, rtol=0)
            np.testing.assert_allclose(g[:, 10], official_reference[p + "opacities"], atol=1e-4, rtol=0)
            rgb = np.maximum(0.28209479 * official_reference[p + "sh_dc"] + 0.5, 0)
            np.testing.assert_allclose(g[:, 11:14], rgb, atol=1e-4, rtol=0)


@pytest.mark.parametrize("frames,targets", [(1, 1), (3, 5), (7, 2)])
def test_dynamic_frame_and_target_counts(package, official_small_dir, frames, targets):
    from c4g.model.config import C4GConfig

    rng = np.random.default_rng(frames * 10 + targets)
    images = rng.uniform(-1, 1, (frames, 3, 224, 224)).astype(np.float32)
    maps = rng.standard_normal((frames, 256, 8)).astype(np.float32)
    times = list(range(frames))
    ctx, tgt = normalise_batch(times, list(np.linspace(0, frames - 1, targets)))
    # The package's own weights (checkpoint + seeded feature decoder), loaded the way the tool did.
    manifest = json.loads((package / "model.json").read_text())
    cfg = C4GConfig.from_dict(manifest["architecture"])
    model = export.build_model(cfg, seed=0, checkpoint=official_small_dir / "c4g_official_small.ckpt")
    with torch.no_grad():
        features = model.encode(torch.from_numpy(images))
        expected = model.decode_canonical(features, torch.from_numpy(ctx), torch.from_numpy(tgt)).numpy()
        expected_features = model.decode_features(features, torch.from_numpy(ctx), torch.from_numpy(tgt), torch.from_numpy(maps)).numpy()
    (got_features,) = session(package / "encoder.onnx").run(None, {"frames": images})
    np.testing.assert_allclose(got_features, features.numpy(), atol=1e-4, rtol=0)
    feed = {"features": features.numpy(), "context_times": ctx, "target_times": tgt}
    (got,) = session(package / "decoder.onnx").run(None, feed)
    np.testing.assert_allclose(got, expected, atol=1e-4, rtol=1e-3)
    got_both, got_lifted = session(package / "feature_decoder.onnx").run(["gaussians", "gaussian_features"], {**feed, "context_feature_maps": maps})
    np.testing.assert_allclose(got_lifted, expected_features, atol=1e-4, rtol=1e-3)
    # The joint decoder's Gaussians are the Gaussian decoder's: the feature stream never feeds back.
    np.testing.assert_allclose(got_both, expected, atol=1e-4, rtol=1e-3)


def test_package_files_are_readable_by_every_user(tmp_path):
    """The export tool's packages are served by another user (the images' `c4g`): every file is
    0644 and every folder 0755 whatever the umask, including external weights, which onnx
    writes 0600."""
    from c4g.package.export import readable_by_all

    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    weights = tmp_path / "pkg" / "encoder.onnx.data"
    weights.write_bytes(b"x")
    weights.chmod(0o600)
    (tmp_path / "pkg" / "sub").chmod(0o700)
    readable_by_all(tmp_path / "pkg")
    assert weights.stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "pkg" / "sub").stat().st_mode & 0o777 == 0o755

