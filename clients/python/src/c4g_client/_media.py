"""What renders come back as: an :class:`Image` (PNG and its pixels), a :class:`ScalarImage`
(raw ``f32`` depth or alpha), a :class:`FeatureImage` (raw ``f32`` lifted features), a
:class:`Video` (MP4). Each shows itself in a notebook.

Jupyter calls ``_repr_png_`` / ``_repr_html_`` when a cell's value is one of these, so
``client.render(clip, t=0.3)`` alone displays the view. The bytes the server sent are kept as
they came (``png``, ``data``): saving one writes exactly what the server rendered. A render
also keeps the scene that served it (``scene``: ``feed-forward`` or ``fitted``, the answer's
``X-C4G-Scene``; ``None`` for what no scene made, such as a context frame).
"""

from __future__ import annotations

import base64
import os
from dataclasses import dataclass, field
from typing import Any, Optional, Union

import numpy as np

from . import _png

PathLike = Union[str, "os.PathLike[str]"]


@dataclass(frozen=True)
class Image:
    """A rendered (or context) image: the server's PNG bytes and, decoded on first use, its
    ``(H, W, 3)`` ``uint8`` pixels."""

    png: bytes
    time: Optional[float] = None
    scene: Optional[str] = None
    _pixels: Any = field(default=None, repr=False, compare=False)

    @property
    def array(self) -> np.ndarray:
        """The pixels, ``(H, W, C)`` ``uint8`` (C = 3 for the server's RGB)."""
        if self._pixels is None:
            object.__setattr__(self, "_pixels", _png.decode(self.png))
        return self._pixels  # type: ignore[no-any-return]

    @property
    def width(self) -> int:
        return int(self.array.shape[1])

    @property
    def height(self) -> int:
        return int(self.array.shape[0])

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return self.array if dtype is None else self.array.astype(dtype)

    def save(self, path: PathLike) -> None:
        """Writes the PNG as the server sent it."""
        with open(path, "wb") as f:
            f.write(self.png)

    def _repr_png_(self) -> bytes:
        return self.png

    def __repr__(self) -> str:
        return f"Image({len(self.png)} bytes of PNG{_when(self.time, self.scene)})"


@dataclass(frozen=True, eq=False)
class ScalarImage:
    """A raw ``f32`` render: expected depth (scene units) or accumulated opacity, ``(H, W)``."""

    array: np.ndarray
    kind: str
    time: Optional[float] = None
    scene: Optional[str] = None

    @property
    def width(self) -> int:
        return int(self.array.shape[1])

    @property
    def height(self) -> int:
        return int(self.array.shape[0])

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return self.array if dtype is None else self.array.astype(dtype)

    def to_uint8(self) -> np.ndarray:
        """Grey levels for display: alpha as is (0..1), depth from its 5th to 95th percentile
        over the pixels something covers (near is bright), empty pixels black."""
        a = np.nan_to_num(self.array.astype(np.float64))
        if self.kind == "alpha":
            return (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)
        covered = a > 0
        if not covered.any():
            return np.zeros(a.shape, dtype=np.uint8)
        low, high = np.percentile(a[covered], [5, 95])
        span = max(high - low, 1e-12)
        grey = 1 - np.clip((a - low) / span, 0, 1)
        return np.where(covered, grey * 255 + 0.5, 0).astype(np.uint8)

    def _repr_png_(self) -> bytes:
        return _png.encode(self.to_uint8())

    def __repr__(self) -> str:
        return f"ScalarImage({self.kind}, {self.width}x{self.height}{_when(self.time, self.scene)})"


@dataclass(frozen=True, eq=False)
class FeatureImage:
    """A raw ``f32`` feature render (format ``features``): each pixel the blending-weighted sum
    of its Gaussians' lifted feature vectors, ``(H, W, F)``, with no background (divide by the
    alpha render for a pixel's mean feature).

    It shows itself as its first three channels, each stretched over its 1st to 99th
    percentile: a quick look only. The clip's own colouring, the same at every time and from
    every camera, is the server's ``features_pca`` render.
    """

    array: np.ndarray
    time: Optional[float] = None
    scene: Optional[str] = None

    @property
    def width(self) -> int:
        return int(self.array.shape[1])

    @property
    def height(self) -> int:
        return int(self.array.shape[0])

    @property
    def channels(self) -> int:
        """Floats per pixel (F, the server's ``X-C4G-Channels``)."""
        return int(self.array.shape[2])

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return self.array if dtype is None else self.array.astype(dtype)

    def to_uint8(self) -> np.ndarray:
        """``(H, W, 3)`` colours of the first three channels (fewer repeat the last)."""
        a = np.nan_to_num(self.array.astype(np.float64))
        picked = a[:, :, [min(k, a.shape[2] - 1) for k in range(3)]]
        low = np.percentile(picked, 1, axis=(0, 1))
        high = np.percentile(picked, 99, axis=(0, 1))
        scaled = np.clip((picked - low) / np.maximum(high - low, 1e-12), 0, 1)
        return (scaled * 255 + 0.5).astype(np.uint8)

    def _repr_png_(self) -> bytes:
        return _png.encode(self.to_uint8())

    def __repr__(self) -> str:
        return f"FeatureImage({self.width}x{self.height}x{self.channels}{_when(self.time, self.scene)})"


@dataclass(frozen=True)
class Video:
    """An MP4 (a trajectory render, a refined result): the bytes, and an inline player."""

    data: bytes
    mime: str = "video/mp4"
    scene: Optional[str] = None

    def save(self, path: PathLike) -> None:
        """Writes the video as the server sent it."""
        with open(path, "wb") as f:
            f.write(self.data)

    def _repr_html_(self) -> str:
        # A data URL keeps the notebook self-contained; trajectory videos are small.
        encoded = base64.b64encode(self.data).decode("ascii")
        return (
            f'<video controls loop autoplay muted playsinline style="max-width: 100%">'
            f'<source src="data:{self.mime};base64,{encoded}" type="{self.mime}"></video>'
        )

    def __len__(self) -> int:
        return len(self.data)

    def __repr__(self) -> str:
        return f"Video({len(self.data)} bytes of {self.mime}{_when(None, self.scene)})"


def _when(time: Optional[float], scene: Optional[str]) -> str:
    """``, t=0.3 s, fitted``: what a render's repr says of its time and scene."""
    parts = ([] if time is None else [f"t={time:g} s"]) + ([] if scene is None else [scene])
    return "".join(f", {part}" for part in parts)
