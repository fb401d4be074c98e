"""Loading checkpoints in the official C4G layout: a Lightning checkpoint whose `state_dict` keys carry
the prefix `encoder.`. Keys must match exactly; a mismatch names every missing or unexpected key. The
keys of parts the official model has and inference never runs are dropped, and the reader says which,
how many parameters they hold, and why, to whoever asks (the export tool prints it)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Callable

import torch

from .config import C4GConfig
from .network import C4G, is_feature_stream

PREFIX = "encoder."
# Present in the official checkpoint (62 keys, 32.7M parameters), unused at inference: dropped, with
# the reason the reader gives for each.
IGNORED = {
    "dpt_head.": "the DPT head, which the official code runs only to visualise a depth map; "
    "no Gaussian depends on it, so inference needs none of it",
}


class CheckpointError(ValueError):
    pass


def read_state_dict(path: str | Path, report: Callable[[str], object] | None = None) -> dict[str, torch.Tensor]:
    """The model's parameters from a checkpoint file, with the `encoder.` prefix removed and the
    `IGNORED` parts dropped; `report` is given one line for each part dropped (`ignored_parts`)."""
    ckpt = torch.load(Path(path), map_location="cpu", weights_only=True)
    state = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: expected a checkpoint dict with a 'state_dict' (official layout)")
    foreign = sorted(k for k in state if not k.startswith(PREFIX))
    if foreign:
        raise CheckpointError(f"{path}: keys without the '{PREFIX}' prefix of the official layout: {_listing(foreign)}")
    stripped = {k[len(PREFIX) :]: v for k, v in state.items()}
    if report is not None:
        for line in ignored_parts(stripped):
            report(line)
    return {k: v for k, v in stripped.items() if not k.startswith(tuple(IGNORED))}


def ignored_parts(state: dict[str, torch.Tensor]) -> list[str]:
    """What of a state dict (without the prefix) is dropped, one line a part: its keys, their
    parameters, and why."""
    lines = []
    for prefix, why in IGNORED.items():
        keys = [k for k in state if k.startswith(prefix)]
        if keys:
            parameters = sum(state[k].numel() for k in keys)
            count = f"{len(keys)} key{'s' if len(keys) != 1 else ''}"
            lines.append(f"dropped {count} of {PREFIX}{prefix}* ({_parameters(parameters)}): {why}")
    return lines


def feature_dim_of(state: dict[str, torch.Tensor]) -> int:
    """The feature stream's width in a state dict (without the prefix): the width of its final norm
    `gmae_decoder.y_norm`, or 0 when the checkpoint has no feature stream."""
    norm = state.get("gmae_decoder.y_norm.weight")
    return int(norm.shape[0]) if norm is not None else 0


def load_into(model: C4G, state: dict[str, torch.Tensor], allow_missing_feature_stream: bool = True) -> None:
    """Strict load: every model key present, no unexpected key, every shape equal.

    The official checkpoint has no feature stream; its weights may be missing when
    `allow_missing_feature_stream` (they keep their initialisation, and the caller says so)."""
    expected = model.state_dict()
    missing = sorted(k for k in expected if k not in state)
    if allow_missing_feature_stream:
        missing = [k for k in missing if not is_feature_stream(k)]
    unexpected = sorted(k for k in state if k not in expected)
    wrong_shape = sorted(
        f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in expected
        if k in state and state[k].shape != expected[k].shape
    )
    problems = []
    if missing:
        problems.append(f"{len(missing)} missing key(s): {_listing([PREFIX + k for k in missing])}")
    if unexpected:
        problems.append(f"{len(unexpected)} unexpected key(s): {_listing([PREFIX + k for k in unexpected])}")
        width = feature_dim_of(state)
        if width != model.cfg.feature_dim and any(is_feature_stream(k) for k in unexpected):
            problems.append(f"the checkpoint has a feature stream of width {width} (the configuration: feature_dim {model.cfg.feature_dim})")
    if wrong_shape:
        problems.append(f"{len(wrong_shape)} shape mismatch(es): {_listing(wrong_shape)}")
    if problems:
        raise CheckpointError("checkpoint does not match the model configuration: " + "; ".join(problems))
    model.load_state_dict(state, strict=False)


def load_checkpoint(path: str | Path, cfg: C4GConfig) -> C4G:
    model = C4G(cfg)
    load_into(model, read_state_dict(path))
    return model.eval()


def sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _parameters(count: int) -> str:
    return f"{count / 1e6:.1f}M parameters" if count >= 100_000 else f"{count:,} parameter{'s' if count != 1 else ''}"


def _listing(keys: list[str], limit: int = 20) -> str:
    shown = ", ".join(keys[:limit])
    return shown + (f", … ({len(keys) - limit} more)" if len(keys) > limit else "")
