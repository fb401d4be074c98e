"""The C library's ``exp`` and ``log`` over whole arrays, rounded to ``float32``: the values the
Rust code makes with ``f64::exp`` / ``f64::ln`` and ``as f32`` (both call the C library's
functions on Linux), bit for bit, at NumPy's speed.

Why not NumPy's functions alone: its vectorised ``exp`` and ``log`` may differ from the C
library's in the last bit of the ``float64`` (about one value in twenty for ``exp`` on an
AVX-512 machine). A last-bit difference changes the ``float32`` only when the ``float64`` lies
within a few ulps of a point halfway between two ``float32`` values, so NumPy's result is kept
wherever the whole interval of ±2⁻⁴⁹ relative around it (8 to 16 ``float64`` ulps: far more than
two results each within an ulp of the true value can differ) rounds to one ``float32``. The rest,
about one value in ten million and NaNs, goes through :mod:`math`, one call each.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

#: Half the relative width of the interval that must round to one ``float32``.
_MARGIN = 2.0**-49


def exp_f32(values: np.ndarray) -> np.ndarray:
    """``exp`` of each ``float64`` value as the C library computes it, rounded to ``float32``."""
    return _as_c_library(values, np.exp, math.exp)


def log_f32(values: np.ndarray) -> np.ndarray:
    """``log`` of each positive (or NaN) ``float64`` value as the C library computes it, rounded
    to ``float32``."""
    return _as_c_library(values, np.log, math.log)


def _as_c_library(
    values: np.ndarray, vectorised: Callable[[np.ndarray], np.ndarray], scalar: Callable[[float], float]
) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        wide = vectorised(values)
        narrow = wide.astype(np.float32)
        low = (wide * (1.0 - _MARGIN)).astype(np.float32)
        high = (wide * (1.0 + _MARGIN)).astype(np.float32)
    # NaN compares unequal to itself, so a NaN goes the exact way too.
    near = np.flatnonzero((low != narrow) | (high != narrow))
    if len(near):
        flat, exact = narrow.reshape(-1), values.reshape(-1)
        flat[near] = np.array([scalar(v) for v in exact[near].tolist()], dtype=np.float32)
    return narrow
