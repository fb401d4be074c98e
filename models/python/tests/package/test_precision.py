"""Lower-precision packages (c4g.package.precision): c4g-tiny converted to f16 and int8 still runs on ONNX
Runtime's CPU, keeps f32 inputs and outputs, is stamped and declared, and stays close to f32.

Tolerances (measured on c4g-tiny's first test clip, with margin): f16 rounds every weight and activation
to 11 significant bits, 5e-3; int8 quantizes the block MatMuls' weights per tensor and their activations
per run, 0.1 in colour and 0.05 in position. Positions are bounded relative to each Gaussian's distance
from the camera (at least 1 unit): a position is a ray times a depth, so its error grows with depth, and
c4g-tiny v2 has a wall 10 units away, where int8 moved a Gaussian 0.114 units on one CPU (AMD EPYC,
0.024 of its distance) and under 0.1 on another. Both are bounds on the maximum over 512 Gaussians, not
averages."""

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from PIL import Image

from c4g.package import precision

from tests.common import MODELS

TINY = MODELS / "c4g-tiny"
CLIP = TINY / "test-clips" / "seed-2000000"


def frames() -> np.ndarray:
    """Context frames 0, 2, 4, 6 of the test clip, as the encoder takes them."""
    images = [Image.open(CLIP / f"frame-0{i}.png").convert("RGB").resize((64, 64), Image.LANCZOS) for i in (0, 2, 4, 6)]
    return np.stack([np.asarray(im, np.float32).transpose(2, 0, 1) / 127.5 - 1.0 for im in images])


def run(package: Path) -> np.ndarray:
    session = lambda name: ort.InferenceSession(str(package / name), providers=["CPUExecutionProvider"])  # noqa: E731
    (features,) = session("encoder.onnx").run(None, {"frames": frames()})
    context = np.array([[0.0, 1 / 3, 2 / 3, 1.0]] * 3, np.float32)
    targets = np.array([0.2, 0.5, 0.9], np.float32)
    (gaussians,) = session("decoder.onnx").run(None, {"features": features, "context_times": context, "target_times": targets})
    return gaussians


@pytest.fixture(scope="module")
def exact():
    return run(TINY)


@pytest.fixture(scope="module", params=["f16", "int8"])
def converted(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param)
    manifest = precision.convert_package(TINY, out, request.param)
    return request.param, out, manifest


def test_converted_graphs_are_stamped_declared_and_keep_f32_io(converted):
    name, out, manifest = converted
    assert manifest["precision"] == name == json.loads((out / "model.json").read_text())["precision"]
    assert manifest["precision_source"]["package"] == "c4g-tiny"
    for graph in manifest["files"].values():
        model = onnx.load(str(out / graph))
        assert {p.key: p.value for p in model.metadata_props}[precision.PRECISION_KEY] == name
        for value in list(model.graph.input) + list(model.graph.output):
            # query_indices (c4g.model.query_subset) is the one integer input, and keeps its default.
            wanted = onnx.TensorProto.INT64 if value.name == "query_indices" else onnx.TensorProto.FLOAT
            assert value.type.tensor_type.elem_type == wanted, value.name
        if manifest.get("decoder_query_subset") and graph == manifest["files"]["decoder"]:
            assert "query_indices" in {i.name for i in model.graph.initializer}
        assert (out / graph).stat().st_mode & 0o044 == 0o044, "readable by other users"


def test_converted_outputs_are_finite_and_close_to_f32(converted, exact):
    name, out, _ = converted
    got = run(out)
    assert got.shape == exact.shape and np.isfinite(got).all()
    error = np.abs(got - exact).max(axis=(0, 1))
    # Positions relative to each Gaussian's distance from the camera (at least 1): see the module doc.
    position = (np.linalg.norm(got[..., 0:3] - exact[..., 0:3], axis=-1) / np.maximum(np.linalg.norm(exact[..., 0:3], axis=-1), 1.0)).max()
    position_bound, colour_bound = {"f16": (5e-3, 5e-3), "int8": (0.05, 0.1)}[name]
    assert position < position_bound, f"position error {position} of the distance"
    assert error[11:14].max() < colour_bound, f"colour error {error[11:14]}"
    # Rotations stay unit quaternions and opacities probabilities: the head's activations are f32.
    assert np.allclose(np.linalg.norm(got[..., 6:10], axis=-1), 1.0, atol=1e-3)
    assert ((got[..., 10] >= 0) & (got[..., 10] <= 1)).all()


def test_int8_quantizes_only_the_large_matmuls(converted):
    name, out, manifest = converted
    if name != "int8":
        pytest.skip("int8 only")
    chosen = precision.large_matmuls(onnx.load(str(TINY / "decoder.onnx")), precision.DEFAULT_MIN_ELEMENTS)
    # Two blocks of matrices: qkv, out and two MLP in the first; the last layer's qkv exported as
    # three products (q for the query rows alone, `decoder.DecoderAttention.split_projection`), so
    # six there. The time MLP and the Gaussian head stay f32.
    assert len(chosen) == 10 and not any("time_mlp" in n or "to_gaussians" in n for n in chosen)
    assert manifest["precision_source"]["quantized"]["decoder"] == "10 MatMuls in int8"
    ops = {n.op_type for n in onnx.load(str(out / "decoder.onnx")).graph.node}
    assert "DynamicQuantizeLinear" in ops and "MatMul" in ops


def test_only_f32_packages_convert(converted, tmp_path):
    _, out, _ = converted
    with pytest.raises(ValueError, match="already"):
        precision.convert_package(out, tmp_path / "again", "int8")
    assert precision.main(["--package", str(out), "--precision", "f16", "--out", str(tmp_path / "x")]) == 2
