"""The reference preprocessing of a frame, with Pillow as the reference inference script does:
centre-crop to a square of the short side, Lanczos resize on 8-bit data, RGB in [0, 1]."""

from __future__ import annotations

import numpy as np
from PIL import Image


def crop_box(width: int, height: int) -> tuple[int, int, int, int]:
    """(left, top, right, bottom) of the centred square of the short side."""
    side = min(width, height)
    left, top = (width - side) // 2, (height - side) // 2
    return left, top, left + side, top + side


def preprocess_u8(image: Image.Image, size: int) -> np.ndarray:
    """8-bit RGB [size, size, 3] after crop and resize."""
    image = image.convert("RGB")
    return np.asarray(image.crop(crop_box(*image.size)).resize((size, size), Image.LANCZOS))


def to_model_input(rgb_u8: np.ndarray) -> np.ndarray:
    """[..., H, W, 3] u8 → [..., 3, H, W] float32 in [-1, 1], the value range the encoder expects."""
    x = rgb_u8.astype(np.float32) / 255.0
    return np.moveaxis((x - 0.5) / 0.5, -1, -3).copy()
