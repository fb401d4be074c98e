"""A :class:`GaussianSet` as antimatter15's ``.splat`` (32 bytes a Gaussian, what its WebGL viewer
and those derived from it stream): the bytes the server's ``splat`` format answers for the same
set (``formats/src/splat.rs`` is the specification).

Per Gaussian, little endian, no header: position ``3 × f32``, scale ``3 × f32`` (linear, so a
zero scale needs no floor here), colour and opacity ``4 × u8`` (``round(255 · clamp(v, 0, 1))``),
rotation ``4 × u8`` as ``round(128 · q / |q| + 128)`` clamped to 0..255, ``w x y z``. Gaussians
are written largest first by ``scale_x · scale_y · scale_z · opacity`` (the order the viewer's
converter produces, which it relies on to show something useful while loading; ties keep the
set's order). A Gaussian with a non-finite value or a zero rotation is left out; features have
no place in the format.

The arithmetic is the Rust writer's: ``float32`` products, sums and quotients in the same order,
and rounding half away from zero (Rust's ``round``, not NumPy's half to even).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover - typing only
    from ._sets import GaussianSet

#: Bytes per Gaussian.
RECORD = 32

_RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("color", "u1", 4), ("rotation", "u1", 4)])


def encode(s: GaussianSet) -> bytes:
    """The ``.splat`` bytes of ``s``."""
    means, scales, quats = _f32(s.means), _f32(s.scales), _f32(s.quats)
    opacities, colors = _f32(s.opacities), _f32(s.colors)
    writable = (
        np.isfinite(means).all(axis=1)
        & np.isfinite(scales).all(axis=1)
        & np.isfinite(quats).all(axis=1)
        & (quats != 0).any(axis=1)
        & np.isfinite(opacities)
        & np.isfinite(colors).all(axis=1)
    )
    kept = np.flatnonzero(writable)
    size = scales[kept, 0] * scales[kept, 1] * scales[kept, 2] * opacities[kept]
    order = kept[np.argsort(-_total_order(size), kind="stable")]

    out = np.zeros(len(order), dtype=_RECORD)
    out["position"] = means[order]
    out["scale"] = scales[order]
    out["color"][:, 0:3] = _unit_to_byte(colors[order])
    out["color"][:, 3] = _unit_to_byte(opacities[order])
    q = quats[order]
    squares = q * q
    norm = np.sqrt(squares[:, 0] + squares[:, 1] + squares[:, 2] + squares[:, 3])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        out["rotation"] = _to_byte(q / norm[:, None] * np.float32(128) + np.float32(128))
    return out.tobytes()


def _f32(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=np.float32)


def _total_order(keys: np.ndarray) -> np.ndarray:
    """``float32`` keys as int64 that sort as Rust's ``f32::total_cmp`` orders them (negative
    values below −0, below +0, NaNs by their sign), so equal and odd keys sort as there."""
    bits = keys.view(np.int32).astype(np.int64)
    return np.where(bits < 0, bits ^ 0x7FFFFFFF, bits)


def _unit_to_byte(v: np.ndarray) -> np.ndarray:
    return _to_byte(np.clip(v, np.float32(0), np.float32(1)) * np.float32(255))


def _to_byte(v: np.ndarray) -> np.ndarray:
    """Rust's ``v.round().clamp(0.0, 255.0) as u8`` of ``float32`` values: half away from zero,
    and a NaN, which ``as u8`` makes 0, 0. In ``float64``, where ``v ± 0.5`` is exact."""
    wide = v.astype(np.float64)
    rounded = np.where(wide < 0, np.ceil(wide - 0.5), np.floor(wide + 0.5))
    clamped = np.clip(rounded, 0, 255)
    clamped[np.isnan(clamped)] = 0
    return clamped.astype(np.uint8)
