"""A Gaussian set as NumPy arrays in gsplat's conventions, and its PyTorch twin.

The server's canonical layout (``scene/src/gaussians.rs``) is already what gsplat's
``rasterization`` takes, so nothing is converted, only named its way:

========== ======= =====================================================================
field      shape   meaning
========== ======= =====================================================================
means      (N, 3)  centres, first context camera's frame, OpenCV axes (x right, y down,
                   z forward), scene units
quats      (N, 4)  unit quaternions **w x y z** (scalar first), normalised by the server
scales     (N, 3)  **linear** standard deviations (activated: gsplat's trainers keep
                   ``log`` scales and pass ``exp`` of them; the server sends the ``exp``),
                   >= 0 and **can be exactly 0** (see below)
opacities  (N,)    activated, in [0, 1] (not logits)
colors     (N, 3)  RGB, >= 0 and usually <= 1 (no spherical harmonics: degree 0 as RGB)
features   (N, F)  each Gaussian's lifted feature vector (the 4D feature field), or
                   ``None``: only a decode that asks for them (``features=True``) on a
                   package with a feature decoder has them (F is its ``feature_lifting``)
========== ======= =====================================================================

Arrays are ``float32``: the wire's ``f32`` exactly, or its ``f16`` widened (exact too).
``features`` is optional and last, so a set is still made from the five columns alone; every
operation that copies a set (``take``, ``to_torch``, :func:`stack`) carries it along.

A scale of exactly 0 is a flat Gaussian, and common: 258 of c4g-tiny's 512 Gaussians have one
at 0.3 s of its test clip. ``np.log(scales)`` is ``-inf`` there, which poisons a trainer's
parameters or a file; :meth:`GaussianSet.log_scales` floors each scale at ``SCALE_FLOOR``
(``1e-30``, whose ``ln`` is about -69.08) first, the floor of the ``.ply`` (this package's and
the server's). :meth:`GaussianSet.to_ply` and :meth:`GaussianSet.to_splat` write a set as those
files, the server's bytes for the same set, without another request.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Sequence

import numpy as np

from . import _ply, _splat
from ._records import PathLike

if TYPE_CHECKING:  # pragma: no cover - typing only
    import torch


#: The five columns in wire order (C4GS, gRPC), with their widths: the server's names.
WIRE_COLUMNS = (("means", 3), ("scales", 3), ("rotations", 4), ("opacities", 1), ("colors", 3))


@dataclass(frozen=True, eq=False)
class GaussianSet:
    """The Gaussians of a clip at one time (seconds). See the module doc for the layout.

    Not comparable with ``==`` (arrays have no single truth value): compare fields with
    ``np.array_equal``.
    """

    time: float
    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    features: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        shapes = {
            "means": (n, 3),
            "quats": (n, 4),
            "scales": (n, 3),
            "opacities": (n,),
            "colors": (n, 3),
        }
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"{name} has shape {getattr(self, name).shape}; expected {shape}")
        if self.features is not None and (self.features.ndim != 2 or self.features.shape[0] != n):
            raise ValueError(f"features has shape {self.features.shape}; expected ({n}, F)")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def count(self) -> int:
        """Gaussians in the set (N)."""
        return len(self)

    @property
    def feature_width(self) -> int:
        """Floats per feature vector (F); 0 when the set has no features (as gRPC says it)."""
        return 0 if self.features is None else int(self.features.shape[1])

    def arrays(self) -> Dict[str, np.ndarray]:
        """The arrays by name, for ``np.savez(path, **s.arrays())`` or a trainer's dict: the
        five columns, and ``features`` when the set has them."""
        out = {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "colors": self.colors,
        }
        if self.features is not None:
            out["features"] = self.features
        return out

    def take(self, index: Any) -> GaussianSet:
        """The Gaussians at ``index`` (a mask, indices or a slice), same time."""
        return GaussianSet(
            self.time,
            self.means[index],
            self.quats[index],
            self.scales[index],
            self.opacities[index],
            self.colors[index],
            None if self.features is None else self.features[index],
        )

    def log_scales(self) -> np.ndarray:
        """``ln`` of the scales, ``(N, 3)`` ``float32``, each floored at ``SCALE_FLOOR``
        (``1e-30``) first so that a zero scale gives a finite value (about -69.08), not
        ``-inf``: what the ``.ply`` holds, and what a trainer that keeps log scales starts
        from."""
        return _ply.log_scales(self.scales)

    def to_ply(self) -> bytes:
        """The set as a 3D Gaussian splatting ``.ply`` (binary, the layout trainers and viewers
        read: logit opacities, log scales floored at ``SCALE_FLOOR``, degree-0 SH colour,
        ``feat_*`` properties when the set has features): the server's ``ply`` bytes for this
        set but for the header's comment."""
        return _ply.encode(self)

    def to_splat(self) -> bytes:
        """The set as antimatter15's ``.splat`` (32 bytes a Gaussian, largest first; Gaussians
        with a non-finite value or a zero rotation left out; no features): the server's
        ``splat`` bytes for this set."""
        return _splat.encode(self)

    def save(self, path: PathLike) -> None:
        """Writes the set to ``path`` as ``.ply`` or ``.splat``, by the path's extension."""
        name = str(path).lower()
        if name.endswith(".ply"):
            data = self.to_ply()
        elif name.endswith(".splat"):
            data = self.to_splat()
        else:
            raise ValueError(f"{path}: a set is saved as .ply or .splat (the path's extension picks)")
        with open(path, "wb") as f:
            f.write(data)

    def to_torch(self, device: Any = None, dtype: Any = None) -> TorchGaussianSet:
        """The same set as PyTorch tensors on ``device`` (``"cuda"``, ``"cpu"``; default CPU),
        ready for ``gsplat.rasterization``. Needs the ``torch`` extra (PyTorch)."""
        try:
            import torch
        except ImportError as e:
            raise ImportError(f"to_torch needs the torch extra: pip install 'c4g-client[torch]' ({e})") from e

        def tensor(a: np.ndarray) -> torch.Tensor:
            t = torch.from_numpy(np.ascontiguousarray(a))
            return t.to(device=device, dtype=dtype) if (device or dtype) else t

        return TorchGaussianSet(
            self.time,
            tensor(self.means),
            tensor(self.quats),
            tensor(self.scales),
            tensor(self.opacities),
            tensor(self.colors),
            None if self.features is None else tensor(self.features),
        )

    def __repr__(self) -> str:
        features = f", features of {self.feature_width}" if self.features is not None else ""
        return f"GaussianSet(t={self.time:g} s, {len(self)} Gaussians{features})"


@dataclass(frozen=True, eq=False)
class TorchGaussianSet:
    """A :class:`GaussianSet` as ``torch.Tensor`` columns (same names, shapes and meaning)."""

    time: float
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    features: Optional[torch.Tensor] = None

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def __repr__(self) -> str:
        return f"TorchGaussianSet(t={self.time:g} s, {len(self)} Gaussians, {self.means.device})"


def from_columns(
    time: float,
    columns: Sequence[np.ndarray],
    features: Optional[np.ndarray] = None,
    feature_width: int = 0,
) -> GaussianSet:
    """A set from the five wire columns (means, scales, rotations, opacities, colours), each
    flat or shaped, any float dtype; widened to ``float32``. ``features``, flat or shaped, holds
    ``feature_width`` floats per Gaussian (the width is given, not inferred: a set of no
    Gaussians still has one)."""
    means, scales, rotations, opacities, colors = (np.asarray(c, dtype=np.float32) for c in columns)
    n = opacities.size
    return GaussianSet(
        float(time),
        means.reshape(n, 3),
        rotations.reshape(n, 4),
        scales.reshape(n, 3),
        opacities.reshape(n),
        colors.reshape(n, 3),
        None if features is None else np.asarray(features, dtype=np.float32).reshape(n, feature_width),
    )


def from_json(body: Dict[str, Any]) -> List[GaussianSet]:
    """The sets of the gaussians endpoint's JSON answer (``{"frames": [...]}``).

    The server writes each ``f32`` as the shortest decimal that reads back to it, so parsing as
    a double and rounding to ``float32`` gives the server's values bit for bit. A frame with
    ``features`` (one row per Gaussian) gives a set with them.
    """
    sets = []
    for frame in body["frames"]:
        columns = [np.asarray(frame[name], dtype=np.float64).reshape(-1) for name, _ in WIRE_COLUMNS]
        features, width = None, 0
        if "features" in frame:
            features = np.asarray(frame["features"], dtype=np.float64)
            width = features.shape[1] if features.ndim == 2 else 0
        sets.append(from_columns(frame["t"], columns, features, width))
    return sets


def stack(sets: Sequence[GaussianSet]) -> Dict[str, np.ndarray]:
    """Sets of one clip (the same N Gaussians at every time, in the same order: C4G's
    correspondence) as arrays with a leading time axis, plus ``times``; ``features`` (T, N, F)
    too when the sets have them (all of them or none: a feature field with holes in time is
    not one)."""
    if not sets:
        raise ValueError("no sets to stack")
    out: Dict[str, np.ndarray] = {"times": np.array([s.time for s in sets])}
    for name in ("means", "quats", "scales", "opacities", "colors"):
        out[name] = np.stack([getattr(s, name) for s in sets])
    features = [s.features for s in sets if s.features is not None]
    if len(features) == len(sets):
        out["features"] = np.stack(features)
    elif features:
        raise ValueError(f"{len(features)} of {len(sets)} sets have features: all of them or none")
    return out
