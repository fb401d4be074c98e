"""Give an existing package's decoder the `query_indices` input, from the package alone.

    python -m c4g.package.query_subset_upgrade --package models/c4g-tiny

For a package whose checkpoint is not at hand (c4g-tiny's training run is not kept): the decoder's
weights are read back out of its own `decoder.onnx`, the decoder is exported again with the query
subset (`c4g.model.query_subset`), and `model.json` declares `decoder_query_subset`. Nothing else of the
package changes.

Reading the weights back: a graph exported by `c4g.package.export` names each initializer by the exporter's
rules (a parameter's own name, or `onnx::MatMul_*` for a transposed weight, `onnx::Add_*` for a
folded constant), and the same code exporting the same architecture gives the same names. So a
model of the same architecture with random weights is exported once, each of its initializers is
matched by value to the parameter it came from (and how: as is, transposed, with a leading axis,
or cast to float), and the package's initializer of the same name gives that parameter back.

Two checks before anything is written, both bit for bit (the graphs compute the same operations on
the same values): the decoder exported again *without* the subset gives exactly the package's
Gaussians, which proves every weight came back; and the new decoder gives them too, given every
query index and given none (it defaults to every query). Only the plain decoder form at f32 is read (what c4g-tiny is); other packages are made
again from their checkpoints with `python -m c4g.package.export`. The decoder is exported again as packages
were before the export split the last layer's qkv projection (`decoder.split_query_projection`), so
that it computes exactly what the package's did.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import numpy_helper

from c4g.model.attention import fused_export
from c4g.model.config import C4GConfig
from c4g.model.decoder import split_query_projection
from c4g.model.init import random_init
from c4g.model.network import C4G

from .export import export_plain_decoder, readable_by_all

# How an initializer holds a parameter, and the way back.
_FORMS: dict[str, tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]]] = {
    "as is": (lambda p: p, lambda a: a),
    "transposed": (lambda p: p.T, lambda a: a.T),
    "leading axis": (lambda p: p[None], lambda a: a[0]),
    "as float": (lambda p: p.astype(np.float32), lambda a: a),
}


class UpgradeError(ValueError):
    """The package cannot be upgraded from its decoder alone."""


def _initializers(path: Path) -> dict[str, np.ndarray]:
    return {t.name: numpy_helper.to_array(t) for t in onnx.load(str(path)).graph.initializer}


def _initializer_sources(cfg: C4GConfig, scratch: Path) -> dict[str, tuple[str, str]]:
    """initializer name → (parameter name, form) for a plain decoder of `cfg` exported by this code."""
    probe = C4G(cfg)
    random_init(probe, seed=12345)
    probe.eval()
    with fused_export(True), split_query_projection(False):
        export_plain_decoder(probe, scratch / "probe.onnx")
    params = {k: v.detach().numpy() for k, v in probe.state_dict().items()}
    sources = {}
    for name, value in _initializers(scratch / "probe.onnx").items():
        found = [
            (param, form)
            for param, p in params.items()
            for form, (held, _) in _FORMS.items()
            if held(p).shape == value.shape and held(p).dtype == value.dtype and np.array_equal(held(p), value)
        ]
        if not found:
            raise UpgradeError(f"the exporter's initializer {name} {value.shape} is no parameter of the model")
        sources[name] = found[0]
    return sources


def _decode(path: Path, feeds: dict[str, np.ndarray]) -> np.ndarray:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    # query_indices is an overridable initializer (it defaults to every query), not an input.
    names = {i.name for i in (*session.get_inputs(), *session.get_overridable_initializers())}
    return session.run(["gaussians"], {k: v for k, v in feeds.items() if k in names})[0]


def _probe_feeds(cfg: C4GConfig, n: int) -> dict[str, np.ndarray]:
    """Decoder inputs that reach every weight: random features, three context times and two targets."""
    gen = np.random.default_rng(0)
    return {
        "features": gen.standard_normal((3, cfg.tokens_per_frame, cfg.feature_width)).astype(np.float32),
        "context_times": np.array([[0.0, 0.5, 1.0], [0.0, 0.4, 0.8]], dtype=np.float32),
        "target_times": np.array([0.25, 0.6], dtype=np.float32),
        "query_indices": np.arange(n, dtype=np.int64),
    }


def upgrade(package: Path) -> dict:
    """Give `package`'s decoder the query subset in place; returns the new manifest."""
    manifest = json.loads((package / "model.json").read_text())
    if manifest.get("decoder_query_subset"):
        raise UpgradeError(f"{package}'s decoder already takes query_indices")
    if manifest.get("decoder_form", "plain") != "plain" or manifest.get("precision", "f32") != "f32":
        raise UpgradeError("only plain-form f32 decoders are read back; export the package again from its checkpoint")
    cfg = C4GConfig.from_dict(manifest["architecture"])
    decoder = package / manifest["files"]["decoder"]
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        sources = _initializer_sources(cfg, scratch)
        held = _initializers(decoder)
        if set(held) != set(sources):
            raise UpgradeError(f"{decoder} was not exported by this code's exporter: its initializers differ")
        model = C4G(cfg)
        random_init(model, seed=0)
        state = model.state_dict()
        for name, (param, form) in sources.items():
            state[param] = torch.from_numpy(np.array(_FORMS[form][1](held[name]), copy=True)).to(state[param].dtype)
        model.load_state_dict(state)
        model.eval()
        feeds = _probe_feeds(cfg, cfg.queries)
        expected = _decode(decoder, feeds)
        with fused_export(manifest.get("attention") == "fused"), split_query_projection(False):
            export_plain_decoder(model, scratch / "again.onnx")
            export_plain_decoder(model, scratch / "subset.onnx", query_subset=True)
        if not np.array_equal(_decode(scratch / "again.onnx", feeds), expected):
            raise UpgradeError("the weights read back do not reproduce the package's decoder")
        without = {k: v for k, v in feeds.items() if k != "query_indices"}
        for given in (feeds, without):
            if not np.array_equal(_decode(scratch / "subset.onnx", given), expected):
                raise UpgradeError("the decoder with every query index does not reproduce the package's decoder")
        (scratch / "subset.onnx").replace(decoder)
    # Beside decoder_form, where a reader of model.json looks for how the decoder is fed.
    upgraded = {}
    for key, value in manifest.items():
        upgraded[key] = value
        if key == "precision":
            upgraded["decoder_query_subset"] = True
    (package / "model.json").write_text(json.dumps(upgraded, indent=2) + "\n")
    readable_by_all(package)
    return upgraded


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.package.query_subset_upgrade", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--package", type=Path, required=True, help="package to upgrade in place")
    args = ap.parse_args(argv)
    try:
        upgrade(args.package)
    except UpgradeError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{args.package}: decoder.onnx takes query_indices (checked bit for bit against the old one)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
