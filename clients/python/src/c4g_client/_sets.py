"""A Gaussian set as NumPy arrays in gsplat's conventions, and its PyTorch twin.

The server's canonical layout (``renderer/src/gaussians.rs``) is already what gsplat's
``rasterization`` takes, so nothing is converted, only named its way:

========== ======= =====================================================================
field      shape   meaning
========== ======= =====================================================================
means      (N, 3)  centres, first context camera's frame, OpenCV axes (x right, y down,
                   z forward), scene units
quats      (N, 4)  unit quaternions **w x y z** (scalar first), normalised by the server
scales     (N, 3)  **linear** standard deviations (activated: gsplat's trainers keep
                   ``log`` scales and pass ``exp`` of them; the server sends the ``exp``)
opacities  (N,)    activated, in [0, 1] (not logits)
colors     (N, 3)  RGB, >= 0 and usually <= 1 (no spherical harmonics: degree 0 as RGB)
========== ======= =====================================================================

Arrays are ``float32``: the wire's ``f32`` exactly, or its ``f16`` widened (exact too).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Dict, List, Sequence

import numpy as np

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

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def count(self) -> int:
        """Gaussians in the set (N)."""
        return len(self)

    def arrays(self) -> Dict[str, np.ndarray]:
        """The five arrays by name, for ``np.savez(path, **s.arrays())`` or a trainer's dict."""
        return {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "colors": self.colors,
        }

    def take(self, index: Any) -> GaussianSet:
        """The Gaussians at ``index`` (a mask, indices or a slice), same time."""
        return GaussianSet(
            self.time,
            self.means[index],
            self.quats[index],
            self.scales[index],
            self.opacities[index],
            self.colors[index],
        )

    def to_torch(self, device: Any = None, dtype: Any = None) -> TorchGaussianSet:
        """The same set as PyTorch tensors on ``device`` (``"cuda"``, ``"cpu"``; default CPU),
        ready for ``gsplat.rasterization``. Needs the ``torch`` extra."""
        import torch

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
        )

    def __repr__(self) -> str:
        return f"GaussianSet(t={self.time:g} s, {len(self)} Gaussians)"


@dataclass(frozen=True, eq=False)
class TorchGaussianSet:
    """A :class:`GaussianSet` as ``torch.Tensor`` columns (same names, shapes and meaning)."""

    time: float
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def __repr__(self) -> str:
        return f"TorchGaussianSet(t={self.time:g} s, {len(self)} Gaussians, {self.means.device})"


def from_columns(time: float, columns: Sequence[np.ndarray]) -> GaussianSet:
    """A set from the five wire columns (means, scales, rotations, opacities, colours), each
    flat or shaped, any float dtype; widened to ``float32``."""
    means, scales, rotations, opacities, colors = (np.asarray(c, dtype=np.float32) for c in columns)
    n = opacities.size
    return GaussianSet(
        float(time),
        means.reshape(n, 3),
        rotations.reshape(n, 4),
        scales.reshape(n, 3),
        opacities.reshape(n),
        colors.reshape(n, 3),
    )


def from_json(body: Dict[str, Any]) -> List[GaussianSet]:
    """The sets of the gaussians endpoint's JSON answer (``{"frames": [...]}``).

    The server writes each ``f32`` as the shortest decimal that reads back to it, so parsing as
    a double and rounding to ``float32`` gives the server's values bit for bit.
    """
    sets = []
    for frame in body["frames"]:
        sets.append(
            from_columns(
                frame["t"],
                [np.asarray(frame[name], dtype=np.float64).reshape(-1) for name, _ in WIRE_COLUMNS],
            )
        )
    return sets


def stack(sets: Sequence[GaussianSet]) -> Dict[str, np.ndarray]:
    """Sets of one clip (the same N Gaussians at every time, in the same order: C4G's
    correspondence) as arrays with a leading time axis, plus ``times``."""
    if not sets:
        raise ValueError("no sets to stack")
    out: Dict[str, np.ndarray] = {"times": np.array([s.time for s in sets])}
    for name in ("means", "quats", "scales", "opacities", "colors"):
        out[name] = np.stack([getattr(s, name) for s in sets])
    return out
