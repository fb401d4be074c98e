"""Timestamp normalisation for the decoder, mirroring the engine's TimePolicy (engine/src/time.rs).

`reference`: rel(t) = (t - min(context)) / (target - min(context) + 1e-8), in float32, as the public
reference code does. It blows up when the target is at (or near) the first context frame.
`stable` (the default): rel(t) = (t - m) / max(target - m, h), h = the mean spacing of the distinct
context times (every time is 0 when there is one instant). It equals the reference for targets at least
one mean spacing after the first frame, is continuous in the target, and stays bounded by n - 1.
Both reject non-finite times and targets outside the context span: the model cannot extrapolate.
"""

from __future__ import annotations

import math

import numpy as np


class TimeError(ValueError):
    pass


def _check(context: list[float], target: float) -> tuple[float, float]:
    if not context:
        raise TimeError("no context times")
    bad = [t for t in list(context) + [target] if not math.isfinite(t)]
    if bad:
        raise TimeError(f"timestamps must be finite numbers, got {bad[0]}")
    m, mx = min(context), max(context)
    if not m <= target <= mx:
        raise TimeError(
            f"target time {target} is outside the context span [{m}, {mx}]: the model interpolates between"
            " context frames and cannot extrapolate"
        )
    return m, mx


def normalise(context: list[float], target: float, policy: str = "stable") -> tuple[np.ndarray, np.float32]:
    """Normalised (context times [T] as float32, target time as float32) for one target."""
    m, mx = _check(context, target)
    if policy == "reference":
        c = np.asarray(context, dtype=np.float32)
        m32, t32 = np.float32(m), np.float32(target)
        denom = (t32 - m32) + np.float32(1e-8)
        return ((c - m32) / denom).astype(np.float32), np.float32((t32 - m32) / denom)
    if policy != "stable":
        raise ValueError(f"unknown time policy {policy!r}")
    distinct = len(set(context))
    if distinct == 1:
        return np.zeros(len(context), np.float32), np.float32(0.0)
    spacing = (mx - m) / (distinct - 1)
    denom = max(target - m, spacing)
    rel = [(t - m) / denom for t in context]
    return np.asarray(rel, dtype=np.float32), np.float32((target - m) / denom)


def normalise_batch(context: list[float], targets: list[float], policy: str = "stable") -> tuple[np.ndarray, np.ndarray]:
    """context_times [B, T] and target_times [B] for the decoder."""
    rows = [normalise(context, t, policy) for t in targets]
    return np.stack([r[0] for r in rows]), np.asarray([r[1] for r in rows], dtype=np.float32)
