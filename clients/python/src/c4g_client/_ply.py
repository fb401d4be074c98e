"""A :class:`GaussianSet` as the 3D Gaussian splatting ``.ply``, the bytes the server's ``ply``
format answers for the same set (``formats/src/ply.rs`` is the specification; only the header's
comment, which names the writer, differs).

Binary little endian, one ``vertex`` element per Gaussian, float properties in the order
trainers use: ``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1
rot_2 rot_3``, then ``feat_0 .. feat_{F-1}`` when the set has features. Values are stored before
activation, as trainers keep them:

- opacity as its logit ``ln(o / (1 − o))``, ``o`` clamped to ``[1e-7, 1 − 1e-7]`` first, so the
  file holds no infinities;
- scales as their logarithm, each floored at :data:`SCALE_FLOOR` (``1e-30``) first: a scale can
  be exactly 0 (a flat Gaussian), and ``ln 0`` is ``−∞``; ``ln 1e-30`` is about −69.08;
- colour as the degree-0 spherical-harmonic coefficient ``(rgb − 0.5) / C0``,
  ``C0 = 1 / (2 √π)``;
- rotations as ``rot_0..3 = w, x, y, z``; normals as zeros.

Each value is computed as the Rust writer computes it, in ``float64`` and then rounded to
``float32``, the logarithms by the C library's ``log`` (``_libm``), so the bytes are the server's.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ._libm import log_f32

if TYPE_CHECKING:  # pragma: no cover - typing only
    from ._sets import GaussianSet

#: The degree-0 spherical-harmonic constant, ``1 / (2 √π)``.
SH_C0 = 0.28209479177387814
#: Opacities are clamped to ``[OPACITY_EPS, 1 − OPACITY_EPS]`` before the logit.
OPACITY_EPS = 1e-7
#: Scales are floored at this before their logarithm (``formats/src/ply.rs``'s ``SCALE_MIN``).
SCALE_FLOOR = 1e-30

_PROPERTIES = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)  # fmt: skip


def log_scales(scales: np.ndarray) -> np.ndarray:
    """``ln(max(scale, SCALE_FLOOR))`` as ``float32``: finite for every finite scale, 0 included
    (a NaN scale is floored too, as Rust's ``f64::max`` does)."""
    return log_f32(np.fmax(np.asarray(scales, dtype=np.float64), SCALE_FLOOR))


def logit_opacities(opacities: np.ndarray) -> np.ndarray:
    """``ln(o / (1 − o))`` of each opacity clamped to ``[1e-7, 1 − 1e-7]``, as ``float32`` (a NaN
    stays NaN: the file keeps what the set held)."""
    o = np.clip(np.asarray(opacities, dtype=np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    return log_f32(o / (1.0 - o))


def encode(s: GaussianSet) -> bytes:
    """The ``.ply`` bytes of ``s``."""
    n = len(s)
    width = s.feature_width
    names = _PROPERTIES + tuple(f"feat_{k}" for k in range(width))
    header = "ply\nformat binary_little_endian 1.0\ncomment written by c4g-client\n"
    header += f"element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"
    rows = np.zeros((n, len(names)), dtype="<f4")
    rows[:, 0:3] = s.means
    rows[:, 6:9] = ((s.colors.astype(np.float64) - 0.5) / SH_C0).astype(np.float32)
    rows[:, 9] = logit_opacities(s.opacities)
    rows[:, 10:13] = log_scales(s.scales)
    rows[:, 13:17] = s.quats
    if s.features is not None:
        rows[:, 17:] = s.features
    return header.encode("ascii") + rows.tobytes()
