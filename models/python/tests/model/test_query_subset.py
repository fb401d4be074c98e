"""Decoding a subset of the queries (c4g.model.query_subset) in the mirror and in the exported graphs.

The independent reference for a subset: the same model with only those queries, i.e. a model
whose `gaussian_tokens` and anchors hold just the kept rows, decoded by the mirror's ordinary full
decode (`C4G.decode_canonical`, no index anywhere). The subset decode must equal it:
- in float64 to 1e-10 (the same operations on the same values; rounding of sums of ~1000 terms),
  for the plain and the precomputed form, for every index, for a strict subset and for one query;
- in float32 to 1e-5 (the precomputed form sums the first layer in another order: about 2e-6);
- exported to ONNX (both forms): within 1e-4 of the mirror (the project's parity tolerance), and
  with `query_indices` left out, the full decode bit for bit (it defaults to every query).
The upgrade tool reads a package's decoder weights back from its graph and gives it the input.
"""

import copy
import dataclasses
import json

import numpy as np
import onnxruntime as ort
import pytest
import torch

from c4g.model.config import OFFICIAL_SMALL
from c4g.model.decoder import split_query_projection
from c4g.model.init import random_init
from c4g.model.network import C4G
from c4g.model.precomputed import ContextProjection, PrecomputedDecoder
from c4g.model.query_subset import decode_canonical_subset, decode_canonical_subset_precomputed
from c4g.package import export, query_subset_upgrade

N = OFFICIAL_SMALL.queries
SUBSETS = {"all": list(range(N)), "strict": [0, 3, 17, 100, 101, N - 1], "one": [42]}


@pytest.fixture(scope="module")
def model() -> C4G:
    m = C4G(OFFICIAL_SMALL)
    random_init(m, seed=5)
    return m.eval()


def only_queries(model: C4G, indices: list[int]) -> C4G:
    """The reference: a model holding only the queries `indices` (their tokens and anchors)."""
    small = C4G(dataclasses.replace(model.cfg, queries=len(indices)))
    state = model.state_dict()
    state["gaussian_tokens"] = state["gaussian_tokens"][indices]
    state["anchor_positions"] = state["anchor_positions"][indices]
    small.load_state_dict(state)
    return small.eval().to(model.gaussian_tokens.dtype)


def inputs(dtype, frames=3, batch=2, seed=0):
    gen = torch.Generator().manual_seed(seed)
    features = torch.randn(frames, OFFICIAL_SMALL.tokens_per_frame, OFFICIAL_SMALL.feature_width, generator=gen, dtype=dtype) + 0.5
    ctx = torch.rand(batch, frames, generator=gen, dtype=dtype) * 2
    tgt = torch.rand(batch, generator=gen, dtype=dtype) * 2
    return features, ctx, tgt


@pytest.mark.parametrize("dtype,tolerance", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
@pytest.mark.parametrize("subset", SUBSETS)
def test_a_subset_decodes_like_a_model_of_those_queries_alone(model, dtype, tolerance, subset):
    m = copy.deepcopy(model).to(dtype)
    indices = SUBSETS[subset]
    features, ctx, tgt = inputs(dtype)
    idx = torch.tensor(indices)
    with torch.no_grad():
        expected = only_queries(m, indices).decode_canonical(features, ctx, tgt)
        plain = decode_canonical_subset(m, features, ctx, tgt, idx)
        pre = PrecomputedDecoder(m)
        precomputed = decode_canonical_subset_precomputed(pre, features, ContextProjection(m)(features), ctx, tgt, idx)
    assert plain.shape == (2, len(indices), 14)
    assert (plain - expected).abs().max() < tolerance
    assert (precomputed - expected).abs().max() < tolerance


def test_every_index_in_order_is_the_full_decode_and_a_strict_subset_is_not(model):
    features, ctx, tgt = inputs(torch.float32)
    with torch.no_grad():
        full = model.decode_canonical(features, ctx, tgt)
        every = decode_canonical_subset(model, features, ctx, tgt, torch.arange(N))
        strict = decode_canonical_subset(model, features, ctx, tgt, torch.tensor(SUBSETS["strict"]))
    assert torch.equal(full, every)
    # Queries attend to each other: dropping some moves the others (the approximation measured
    # in docs/tradeoffs.md), here by far more than rounding.
    assert (strict - full[:, SUBSETS["strict"]]).abs().max() > 1e-3


@pytest.fixture(scope="module")
def packages(model, tmp_path_factory):
    root = tmp_path_factory.mktemp("subset")
    for form in ("plain", "precomputed"):
        export.export_package(model, root / form, f"c4g-{form}", "0.1.0", {"kind": "random-init", "seed": 5}, decoder_form=form)
    # As packages were exported before decoders took query_indices: also before the export split
    # the last layer's qkv projection (what the upgrade reads back, like c4g-tiny).
    with split_query_projection(False):
        export.export_package(model, root / "old", "c4g-old", "0.1.0", {"kind": "random-init", "seed": 5}, decoder_form="plain", query_subset=False)
    return root


def run(package, features, ctx, tgt, indices=None):
    feed = {"features": features, "context_times": ctx, "target_times": tgt}
    cpu = ["CPUExecutionProvider"]
    if (package / "context_projection.onnx").exists():
        (feed["context_projection"],) = ort.InferenceSession(str(package / "context_projection.onnx"), providers=cpu).run(None, {"features": features})
    if indices is not None:
        feed["query_indices"] = np.asarray(indices, dtype=np.int64)
    return ort.InferenceSession(str(package / "decoder.onnx"), providers=cpu).run(None, feed)[0]


@pytest.mark.parametrize("form", ["plain", "precomputed"])
def test_exported_decoders_take_any_subset_and_default_to_all(model, packages, form):
    assert json.loads((packages / form / "model.json").read_text())["decoder_query_subset"] is True
    features, ctx, tgt = (x.numpy() for x in inputs(torch.float32, frames=4, batch=3, seed=1))
    with torch.no_grad():
        full = model.decode_canonical(*(torch.from_numpy(x) for x in (features, ctx, tgt))).numpy()
    assert np.abs(run(packages / form, features, ctx, tgt) - full).max() < 1e-4
    for indices in SUBSETS.values():
        with torch.no_grad():
            expected = only_queries(model, indices).decode_canonical(*(torch.from_numpy(x) for x in (features, ctx, tgt))).numpy()
        got = run(packages / form, features, ctx, tgt, indices)
        assert got.shape == (3, len(indices), 14)
        assert np.abs(got - expected).max() < 1e-4, indices


def test_without_the_subset_the_decoder_is_as_before(packages):
    manifest = json.loads((packages / "old/model.json").read_text())
    assert "decoder_query_subset" not in manifest
    session = ort.InferenceSession(str(packages / "old/decoder.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["features", "context_times", "target_times"]
    assert session.get_overridable_initializers() == []


def test_the_upgrade_reads_the_weights_back_and_adds_the_input(packages, tmp_path):
    old = tmp_path / "old"
    old.mkdir()
    for path in (packages / "old").iterdir():
        (old / path.name).write_bytes(path.read_bytes())
    features, ctx, tgt = (x.numpy() for x in inputs(torch.float32, seed=2))
    before = run(old, features, ctx, tgt)
    manifest = query_subset_upgrade.upgrade(old)
    assert manifest["decoder_query_subset"] is True
    assert np.array_equal(run(old, features, ctx, tgt), before)
    assert np.array_equal(run(old, features, ctx, tgt, range(N)), before)
    assert np.abs(run(old, features, ctx, tgt, SUBSETS["strict"]) - run(packages / "plain", features, ctx, tgt, SUBSETS["strict"])).max() < 1e-6
    with pytest.raises(query_subset_upgrade.UpgradeError, match="already"):
        query_subset_upgrade.upgrade(old)
