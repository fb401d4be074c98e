"""Timestamp normalisation for the decoder, mirroring the engine's TimePolicy (engine/src/time.rs).

`reference`: rel(t) = (t - min(context)) / (target - min(context) + 1e-8), in float32, as the public
reference code does. It blows up when the target is at (or near) the first context frame.
`frame-step` (the engine's default for packages that declare no policy, i.e. the official weights):
rel(t) = (t - m) / max(target - m, s), s = the source's frame step (seconds between source frames) or,
when unknown, the smallest gap between distinct context times. It equals the reference for every target
at least one source frame after the first context frame (where the official weights were trained: they
saw integer frame indices), is continuous in the target, and stays bounded by (M - m) / s.
`stable` (the default here: what our own models, c4g-tiny, are trained with): rel(t) = (t - m) / max(target - m, h),
h = the mean spacing of the distinct context times. It equals the reference for targets at least one mean
spacing after the first frame, is continuous in the target, and stays bounded by n - 1.
Every time is 0 when the context is one instant. All reject non-finite times, a frame step that is not a
positive finite number, targets outside the context span (the model cannot extrapolate) and results that
would not be finite.

    python -m c4g.model.time_policy --write-cases models/fixtures/time-policy-cases.json

writes the table of cases the engine's tests hold the Rust policies to (bit for bit).
"""

from __future__ import annotations

import argparse
import json
import math
import struct
from pathlib import Path

import numpy as np

POLICIES = ("frame-step", "stable", "reference")


class TimeError(ValueError):
    pass


def _check(context: list[float], target: float, frame_step: float | None) -> tuple[float, float]:
    if not context:
        raise TimeError("no context times")
    bad = [t for t in list(context) + [target] if not math.isfinite(t)]
    if bad:
        raise TimeError(f"timestamps must be finite numbers, got {bad[0]}")
    if frame_step is not None and not (math.isfinite(frame_step) and frame_step > 0):
        raise TimeError(f"a source frame step must be a positive, finite number of seconds, got {frame_step}")
    m, mx = min(context), max(context)
    if not m <= target <= mx:
        raise TimeError(
            f"target time {target} is outside the context span [{m}, {mx}]: the model interpolates between"
            " context frames and cannot extrapolate"
        )
    if not math.isfinite(mx - m):
        raise TimeError(f"normalising times over the context span [{m}, {mx}] does not give finite values")
    return m, mx


def smallest_gap(context: list[float]) -> float | None:
    """The smallest gap between distinct context times (None for one instant): the fallback frame step."""
    distinct = sorted({t + 0.0 for t in context})
    gaps = [b - a for a, b in zip(distinct, distinct[1:])]
    return min(gaps) if gaps else None


def normalise(
    context: list[float], target: float, policy: str = "stable", frame_step: float | None = None
) -> tuple[np.ndarray, np.float32]:
    """Normalised (context times [T] as float32, target time as float32) for one target.

    `frame_step` (seconds between source frames, None: unknown) is read by `frame-step` only."""
    if policy not in POLICIES:
        raise ValueError(f"unknown time policy {policy!r}")
    m, mx = _check(context, target, frame_step)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        ctx, tgt = _POLICY[policy](context, target, m, mx, frame_step)
    if not (np.all(np.isfinite(ctx)) and np.isfinite(tgt)):
        raise TimeError(f"normalising times over the context span [{m}, {mx}] does not give finite values")
    return ctx, tgt


def _reference(context, target, m, mx, frame_step):
    c = np.asarray(context, dtype=np.float32)
    m32, t32 = np.float32(m), np.float32(target)
    denom = (t32 - m32) + np.float32(1e-8)
    return ((c - m32) / denom).astype(np.float32), np.float32((t32 - m32) / denom)


def _stable(context, target, m, mx, frame_step):
    distinct = len(set(context))
    if distinct == 1:
        return np.zeros(len(context), np.float32), np.float32(0.0)
    intervals = distinct - 1
    spacing = (mx - m) / intervals
    denom = max(target - m, spacing)
    # The engine's clamp: it only bites where rounding (subnormal spans) would pass the bound.
    rel = [min((t - m) / denom, intervals) for t in context]
    return np.asarray(rel, dtype=np.float32), np.float32(min((target - m) / denom, intervals))


def _frame_step(context, target, m, mx, frame_step):
    step = frame_step if frame_step is not None else smallest_gap(context)
    if step is None or mx == m:
        return np.zeros(len(context), np.float32), np.float32(0.0)
    first = m + 0.0
    denom = max(target - first, step)
    rel = [(t + 0.0 - first) / denom for t in context]
    return np.asarray(rel, dtype=np.float32), np.float32((target + 0.0 - first) / denom)


_POLICY = {"reference": _reference, "stable": _stable, "frame-step": _frame_step}


def normalise_batch(
    context: list[float], targets: list[float], policy: str = "stable", frame_step: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """context_times [B, T] and target_times [B] for the decoder."""
    rows = [normalise(context, t, policy, frame_step) for t in targets]
    return np.stack([r[0] for r in rows]), np.asarray([r[1] for r in rows], dtype=np.float32)


# The cross-check table: inputs and this mirror's outputs, as IEEE bit patterns (f64 in, f32 out).


def _f64_bits(x: float) -> int:
    return struct.unpack("<Q", struct.pack("<d", float(x)))[0]


def _f32_bits(x) -> int:
    return int(np.asarray(x, dtype=np.float32).view(np.uint32))


def _case_inputs(seed: int = 12) -> list[tuple[str, list[float], float | None, float]]:
    """Deterministic (policy, context, frame step, target) cases: the hand-picked ones of the docs and
    tests, then seeded random contexts in seconds and in frame indices, with targets at context frames,
    inside the first source frame, between frames and outside the span."""
    hand: list[tuple[list[float], float | None, float]] = [
        ([0, 2, 4, 6], None, 1), ([0, 2, 4, 6], 1 / 30, 1), ([0, 2, 4, 6], 1 / 30, 0), ([0, 2, 4, 6], 1 / 30, 0.01),
        ([0, 2, 4, 6], 1.0, 0.5), ([0, 2, 4, 6], 1.0, 6), ([0, 2, 2.5, 6], None, 0.25), ([6, 0, 4, 2], 1.0, 0.5),
        ([0, 0, 2, 4, 4, 6], None, 1), ([5.0], None, 5.0), ([5.0], 0.1, 5.0), ([3, 3, 3], 0.5, 3),
        ([-1.5, -0.5, 0.5], None, 0.0), ([-0.0, 0.0, 1.0], 0.5, 0.0), ([0, 2, 4, 6], None, 7),
        ([0, 2, 4, 6], None, -0.5), ([0, 2, 4, 6], 0.0, 1), ([0, 2, 4, 6], -1.0, 1), ([0, 2, 4, 6], math.nan, 1),
        ([0, 2, 4, 6], math.inf, 1), ([0, math.nan], None, 0), ([0, 1], None, math.nan), ([0, 1e300], 1e-300, 0),
        ([0, 1e-300, 1], None, 0), ([0, 2, 4, 6], 1e6, 3), ([10, 12, 14, 16], 0.25, 10.25 - 1e-9),
    ]
    cases = [(p, [float(t) for t in c], s, float(x)) for c, s, x in hand for p in POLICIES]
    rng = np.random.default_rng(seed)
    for k in range(48):
        n = int(rng.integers(1, 9))
        kind = k % 3
        if kind == 0:  # seconds at a frame rate, a strided subset of the source frames
            fps = float(rng.choice([24.0, 25.0, 30.0, 60.0, 29.97]))
            frames = np.sort(rng.choice(200, size=n, replace=bool(rng.integers(0, 2))))
            context = [float(f) / fps for f in frames]
            step = 1 / fps if rng.random() < 0.75 else None
        elif kind == 1:  # raw frame indices, as in training
            context = [float(f) for f in np.sort(rng.choice(100, size=n, replace=bool(rng.integers(0, 2))))]
            step = 1.0 if rng.random() < 0.75 else None
        else:  # arbitrary seconds, unsorted
            context = [float(t) for t in rng.uniform(-5, 5, n)]
            step = float(rng.uniform(1e-3, 2)) if rng.random() < 0.5 else None
        m, mx = min(context), max(context)
        s = step or smallest_gap(context) or 1.0
        targets = [m, mx, context[int(rng.integers(0, n))], m + rng.random() * min(s, mx - m),
                   m + rng.random() * (mx - m), mx + 0.5]  # fmt: skip
        for target in targets[int(rng.integers(0, 3)) :: 2]:
            for policy in POLICIES:
                cases.append((policy, context, step, float(target)))
    return cases


def cross_check_cases(seed: int = 12) -> dict:
    """The table engine/src/time.rs reads: every case with the mirror's output, or null when refused."""
    out = []
    for policy, context, step, target in _case_inputs(seed):
        try:
            ctx, tgt = normalise(context, target, policy, step)
            expected = {"context_bits": [_f32_bits(v) for v in ctx], "target_bits": _f32_bits(tgt)}
        except TimeError:
            expected = None
        out.append({
            "readable": f"{policy} context {context!r} step {step!r} target {target!r}",
            "policy": policy,
            "context_bits": [_f64_bits(t) for t in context],
            "frame_step_bits": None if step is None else _f64_bits(step),
            "target_bits": _f64_bits(target),
            "expected": expected,
        })  # fmt: skip
    return {
        "about": "Time-policy cases and the Python mirror's outputs (c4g.model.time_policy), as IEEE bit patterns: "
        "inputs f64, outputs f32; expected null: refused. Rust holds engine/src/time.rs to it; remake with "
        "python -m c4g.model.time_policy --write-cases models/fixtures/time-policy-cases.json",
        "cases": out,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.model.time_policy", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--write-cases", type=Path, required=True, help="where to write the cross-check table (JSON)")
    args = ap.parse_args(argv)
    table = cross_check_cases()
    rows = ",\n".join(json.dumps(case) for case in table["cases"])
    args.write_cases.write_text(f'{{"about": {json.dumps(table["about"])},\n"cases": [\n{rows}\n]}}\n')
    print(f"wrote {args.write_cases} ({len(table['cases'])} cases)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
