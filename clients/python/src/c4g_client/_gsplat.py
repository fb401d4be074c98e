"""Rendering a decoded set with gsplat (``gsplat.rasterization``), so a user can compare the
service's renders with their own pipeline's.

gsplat is not a dependency (it builds CUDA kernels); :func:`render_with_gsplat` imports it when
called and raises :class:`GsplatUnavailable` (an ``ImportError``) where it is missing, and
:func:`gsplat_available` says beforehand. Nothing is converted but the camera: a set's arrays are
already gsplat's (linear scales, wxyz unit quaternions, activated opacities, RGB colours); the
camera's world-to-camera matrix is gsplat's ``viewmats`` (both OpenCV axes), and its intrinsics,
fractions of the image size, become the pixel matrix ``Ks``. Expect small differences from the
server's rasterizer at splat edges: the footprint and the 2D dilation differ slightly
(``GET /v1/models`` says which footprint the server draws).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np

from . import _png
from ._camera import CameraLike, as_camera
from ._media import Image
from ._sets import GaussianSet, TorchGaussianSet


class GsplatUnavailable(ImportError):
    """gsplat (and so its CUDA kernels) is not installed here."""


def gsplat_available() -> bool:
    """Whether ``import gsplat`` would find the package."""
    return importlib.util.find_spec("gsplat") is not None


@dataclass(frozen=True, eq=False)
class GsplatRender:
    """gsplat's render of a set: the colours ``(H, W, 3)`` and alpha ``(H, W)`` as float32
    arrays, and an :class:`~c4g_client.Image` of the colours (8-bit, for display)."""

    colors: np.ndarray
    alpha: np.ndarray
    image: Image

    def _repr_png_(self) -> bytes:
        return self.image.png


def camera_tensors(camera: Optional[CameraLike], width: int, height: int) -> Tuple[np.ndarray, np.ndarray]:
    """gsplat's ``viewmats`` ``(1, 4, 4)`` and ``Ks`` ``(1, 3, 3)`` of a camera, as float32
    NumPy arrays."""
    cam = as_camera(camera)
    intrinsics = cam.intrinsics
    if intrinsics is None:
        from ._camera import Intrinsics

        intrinsics = Intrinsics()
    view = cam.view_matrix().astype(np.float32)[None]
    ks = intrinsics.matrix(width, height).astype(np.float32)[None]
    return view, ks


def render_with_gsplat(
    gaussians: Union[GaussianSet, TorchGaussianSet],
    camera: Optional[CameraLike] = None,
    *,
    width: int,
    height: int,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    device: Any = "cuda",
    **options: Any,
) -> GsplatRender:
    """Renders ``gaussians`` from ``camera`` (default: the first context camera with the
    model's intrinsics, like the server's default view) with ``gsplat.rasterization``;
    ``options`` go to it as they are (``rasterize_mode="antialiased"``, ...)."""
    try:
        import gsplat
        import torch
    except ImportError as e:
        raise GsplatUnavailable(
            f"rendering with gsplat needs gsplat and PyTorch (pip install gsplat): {e}"
        ) from e
    t = gaussians.to_torch(device=device) if isinstance(gaussians, GaussianSet) else gaussians
    view, ks = camera_tensors(camera, width, height)

    def on_device(a: np.ndarray) -> Any:
        return torch.from_numpy(a).to(device=device, dtype=torch.float32)

    colors, alphas, _meta = gsplat.rasterization(
        means=t.means.to(device=device, dtype=torch.float32),
        quats=t.quats.to(device=device, dtype=torch.float32),
        scales=t.scales.to(device=device, dtype=torch.float32),
        opacities=t.opacities.to(device=device, dtype=torch.float32),
        colors=t.colors.to(device=device, dtype=torch.float32),
        viewmats=on_device(view),
        Ks=on_device(ks),
        width=width,
        height=height,
        backgrounds=on_device(np.asarray(background, dtype=np.float32)[None]),
        **options,
    )
    rgb = colors[0, :, :, :3].detach().float().cpu().numpy()
    alpha = alphas[0, :, :, 0].detach().float().cpu().numpy()
    pixels = (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    image = Image(_png.encode(pixels))
    object.__setattr__(image, "_pixels", pixels)
    return GsplatRender(rgb, alpha, image)
