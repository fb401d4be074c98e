"""The precomputed decoder form (c4g.model.precomputed) equals the plain decoder.

- The LayerNorm identity it rests on, W · LN(F + e) = [(Wγ) F̃ + (Wγ) ẽ] / σ + W β with
  σ² = var(F) + 2 F̃ · ẽ / d + var(e) + eps, holds in float64 to rounding (1e-12), also for tokens
  whose mean is far from zero.
- The whole decoder in float64: equal to 1e-10 (rounding of float64 sums of ~1000 terms).
- In float32: within 1e-5 of the plain decoder (measured about 2e-6: the two forms sum the first
  layer's dot products in different orders; the bound leaves room for other CPUs' kernels).
- Exported to ONNX in both forms: both within 1e-4 of the mirror (the project's parity tolerance).
- The exported last layer projects q for the query rows alone, k and v apart (no wide qkv product
  to slice), and gives what the graph with one qkv product gives, within 1e-5.
- The committed fixture `models/fixtures/decoder-forms` still reproduces its stored outputs.
"""

import copy
import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from safetensors.numpy import load_file

from c4g.model.config import OFFICIAL, OFFICIAL_SMALL
from c4g.model.decoder import split_query_projection
from c4g.model.init import random_init
from c4g.model.network import C4G
from c4g.model.precomputed import ContextProjection, PrecomputedDecoder
from c4g.model.time_policy import normalise_batch
from c4g.package import export, precision

from tests.common import MODELS

FORMS = MODELS / "fixtures" / "decoder-forms"


@pytest.fixture(scope="module")
def model() -> C4G:
    m = C4G(OFFICIAL_SMALL)
    random_init(m, seed=3)
    return m.eval()


def times(frames: int, batch: int, gen: torch.Generator, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.rand(batch, frames, generator=gen, dtype=dtype) * 2, torch.rand(batch, generator=gen, dtype=dtype) * 2


def test_the_layer_norm_identity_holds_in_float64():
    gen = torch.Generator().manual_seed(0)
    d, out = 96, 40
    w = torch.randn(out, d, generator=gen, dtype=torch.float64)
    gamma = 1 + 0.3 * torch.randn(d, generator=gen, dtype=torch.float64)
    beta = 0.1 * torch.randn(d, generator=gen, dtype=torch.float64)
    tokens = torch.randn(50, d, generator=gen, dtype=torch.float64) * 3 + torch.linspace(-40, 40, 50, dtype=torch.float64)[:, None]
    emb = torch.relu(torch.randn(d, generator=gen, dtype=torch.float64)) + 5
    eps = 1e-5
    expected = torch.nn.functional.layer_norm(tokens + emb, (d,), gamma, beta, eps) @ w.T
    wg = w * gamma
    f, e = tokens - tokens.mean(-1, keepdim=True), emb - emb.mean()
    sigma = torch.sqrt(f.pow(2).mean(-1) + 2 * (f @ e) / d + e.pow(2).mean() + eps)
    got = (f @ wg.T + e @ wg.T) / sigma[:, None] + w @ beta
    assert torch.allclose(got, expected, atol=1e-12, rtol=0), float((got - expected).abs().max())


@pytest.mark.parametrize("frames,batch", [(1, 1), (3, 2), (5, 4)])
def test_the_precomputed_decoder_equals_the_plain_one_in_float64(model, frames, batch):
    m = copy.deepcopy(model).double()
    gen = torch.Generator().manual_seed(frames * 10 + batch)
    features = torch.randn(frames, 256, 128, generator=gen, dtype=torch.float64) + 0.7
    ctx, tgt = times(frames, batch, gen, torch.float64)
    with torch.no_grad():
        plain = m.decode_canonical(features, ctx, tgt)
        precomputed = PrecomputedDecoder(m).decode_canonical(features, ContextProjection(m)(features), ctx, tgt)
    assert (plain - precomputed).abs().max() < 1e-10


def test_the_precomputed_decoder_equals_the_plain_one_in_float32(model):
    gen = torch.Generator().manual_seed(1)
    features = torch.randn(4, 256, 128, generator=gen)
    ctx, tgt = times(4, 3, gen, torch.float32)
    with torch.no_grad():
        plain = model.decode_canonical(features, ctx, tgt)
        precomputed = PrecomputedDecoder(model).decode_canonical(features, ContextProjection(model)(features), ctx, tgt)
    assert (plain - precomputed).abs().max() < 1e-5


def test_auto_chooses_the_precomputed_form_for_wide_decoders_only():
    assert export.chosen_decoder_form("auto", OFFICIAL) == "precomputed"
    assert export.chosen_decoder_form("auto", OFFICIAL_SMALL) == "plain"
    assert export.chosen_decoder_form("precomputed", OFFICIAL_SMALL) == "precomputed"
    with pytest.raises(ValueError, match="decoder form"):
        export.chosen_decoder_form("cached", OFFICIAL)


@pytest.fixture(scope="module")
def packages(model, tmp_path_factory):
    root = tmp_path_factory.mktemp("forms")
    for form in ("plain", "precomputed"):
        export.export_package(model, root / form, f"c4g-{form}", "0.1.0", {"kind": "random-init", "seed": 3}, decoder_form=form)
    return root


def session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def decode(package: Path, features: np.ndarray, ctx: np.ndarray, tgt: np.ndarray) -> np.ndarray:
    feed = {"features": features, "context_times": ctx, "target_times": tgt}
    if (package / "context_projection.onnx").exists():
        (feed["context_projection"],) = session(package / "context_projection.onnx").run(None, {"features": features})
    (gaussians,) = session(package / "decoder.onnx").run(None, feed)
    return gaussians


def test_the_manifest_declares_the_form_and_its_graph(packages):
    plain = json.loads((packages / "plain/model.json").read_text())
    precomputed = json.loads((packages / "precomputed/model.json").read_text())
    assert plain["decoder_form"] == "plain" and "context_projection" not in plain["files"]
    assert precomputed["decoder_form"] == "precomputed"
    assert precomputed["files"]["context_projection"] == "context_projection.onnx"
    names = lambda path, kind: [v.name for v in getattr(session(path), f"get_{kind}")()]  # noqa: E731
    assert names(packages / "precomputed/context_projection.onnx", "outputs") == ["context_projection"]
    assert names(packages / "precomputed/decoder.onnx", "inputs") == ["features", "context_projection", "context_times", "target_times"]


@pytest.mark.parametrize("frames,batch", [(1, 1), (3, 5), (7, 2)])
def test_both_exported_forms_reproduce_the_mirror(model, packages, frames, batch):
    rng = np.random.default_rng(frames * 10 + batch)
    features = rng.standard_normal((frames, 256, 128)).astype(np.float32)
    ctx, tgt = normalise_batch(list(range(frames)), list(np.linspace(0, frames - 1, batch)))
    with torch.no_grad():
        expected = model.decode_canonical(torch.from_numpy(features), torch.from_numpy(ctx), torch.from_numpy(tgt)).numpy()
    for form in ("plain", "precomputed"):
        got = decode(packages / form, features, ctx, tgt)
        np.testing.assert_allclose(got, expected, atol=1e-4, rtol=1e-3, err_msg=form)


def last_layer_weights(path: Path) -> list[list[int]]:
    """Shapes of the constant right-hand sides of the last decoder layer's attention MatMuls."""
    graph = onnx.load(str(path)).graph
    shapes = {i.name: list(i.dims) for i in graph.initializer}
    last = f"/gmae_decoder/layers.{OFFICIAL_SMALL.decoder_depth - 1}.0/"
    return sorted(shapes[n.input[1]] for n in graph.node if n.op_type == "MatMul" and n.name.startswith(last) and n.input[1] in shapes)


@pytest.mark.parametrize("form", ["plain", "precomputed"])
def test_the_exported_last_layer_projects_q_for_the_query_rows_alone(model, packages, tmp_path, form):
    d, inner = OFFICIAL_SMALL.decoder_dim, OFFICIAL_SMALL.decoder_heads * OFFICIAL_SMALL.decoder_head_dim
    # Three products of width `inner` (q on the query rows, k and v on every row) and to_out.
    assert last_layer_weights(packages / form / "decoder.onnx") == sorted([[d, inner]] * 3 + [[inner, d]])
    with split_query_projection(False):
        export.export_package(model, tmp_path / form, f"c4g-{form}", "0.1.0", {"kind": "random-init", "seed": 3}, decoder_form=form)
    assert last_layer_weights(tmp_path / form / "decoder.onnx") == sorted([[d, 3 * inner], [inner, d]])
    rng = np.random.default_rng(1)
    features = rng.standard_normal((3, 256, d)).astype(np.float32)
    ctx, tgt = normalise_batch([0, 1, 2], [0.5, 1.5, 2.0])
    np.testing.assert_allclose(decode(packages / form, features, ctx, tgt), decode(tmp_path / form, features, ctx, tgt), atol=1e-5, rtol=0)


@pytest.mark.parametrize("name,bound", [("f16", 5e-3), ("int8", 0.1)])
def test_a_precomputed_package_converts_to_lower_precision(packages, tmp_path, name, bound):
    out = tmp_path / name
    manifest = precision.convert_package(packages / "precomputed", out, name, min_elements=4096)
    assert manifest["decoder_form"] == "precomputed" and manifest["precision"] == name
    rng = np.random.default_rng(0)
    features = rng.standard_normal((3, 256, 128)).astype(np.float32)
    ctx, tgt = normalise_batch([0, 1, 2], [0.5, 2.0])
    exact = decode(packages / "precomputed", features, ctx, tgt)
    got = decode(out, features, ctx, tgt)
    assert np.isfinite(got).all()
    assert np.abs(got - exact)[..., [0, 1, 2, 11, 12, 13]].max() < bound


@pytest.mark.skipif(not FORMS.is_dir(), reason="models/fixtures/decoder-forms is not in this checkout")
def test_the_committed_decoder_forms_fixture_reproduces_its_reference():
    ref = load_file(str(FORMS / "reference.safetensors"))
    meta = json.loads((FORMS / "reference.json").read_text())
    for case in meta["cases"]:
        name, t = case["case"], case["frames"]
        ctx, tgt = normalise_batch(case["times"], case["targets"], case["policy"])
        for form in ("plain", "precomputed"):
            package = FORMS / form
            (features,) = session(package / "encoder.onnx").run(None, {"frames": ref["frames"][:t]})
            np.testing.assert_allclose(features, ref[f"{name}/features"], atol=1e-4, rtol=0)
            got = decode(package, features, ctx, tgt)
            np.testing.assert_allclose(got, ref[f"{name}/gaussians"], atol=1e-4, rtol=1e-3, err_msg=f"{name} {form}")
