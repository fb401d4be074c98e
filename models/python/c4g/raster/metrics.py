"""Float64 references of the image metrics in renderer/src/fidelity.rs, and the fixture that pins them.

    python -m c4g.raster.metrics --out models/fixtures/metrics

- `psnr`: 10 log10(1 / MSE) with peak 1, over masked pixels and the three channels.
- `ssim`: Wang et al. with an 11x11 Gaussian window (sigma 1.5, normalised), K1 = 0.01, K2 = 0.03,
  L = 1, 'valid' window positions only, averaged over positions (those whose window centre is masked)
  and channels.

Written independently of the Rust code: the window is applied as a full 2D kernel over
sliding windows (the Rust code filters separably).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from safetensors.numpy import save_file

WINDOW, SIGMA, K1, K2 = 11, 1.5, 0.01, 0.03


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    sel = np.ones(a.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    mse = np.mean((a[sel] - b[sel]) ** 2)
    return float("inf") if mse == 0 else float(-10 * np.log10(mse))


def window() -> np.ndarray:
    r = np.arange(WINDOW) - WINDOW // 2
    g = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * SIGMA**2))
    return g / g.sum()


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    k = window()
    c1, c2 = K1**2, K2**2
    half = WINDOW // 2
    h, w = a.shape[:2]
    centres = np.ones((h - 2 * half, w - 2 * half), bool)
    if mask is not None:
        centres = np.asarray(mask, bool)[half : h - half, half : w - half]
    scores = []
    for c in range(3):
        x = np.lib.stride_tricks.sliding_window_view(a[..., c], (WINDOW, WINDOW))
        y = np.lib.stride_tricks.sliding_window_view(b[..., c], (WINDOW, WINDOW))
        mx = np.einsum("ijkl,kl->ij", x, k)
        my = np.einsum("ijkl,kl->ij", y, k)
        vx = np.einsum("ijkl,kl->ij", (x - mx[..., None, None]) ** 2, k)
        vy = np.einsum("ijkl,kl->ij", (y - my[..., None, None]) ** 2, k)
        cov = np.einsum("ijkl,kl->ij", (x - mx[..., None, None]) * (y - my[..., None, None]), k)
        s = ((2 * mx * my + c1) * (2 * cov + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
        scores.append(s[centres])
    return float(np.mean(np.concatenate(scores)))


def cases(seed: int = 0) -> dict[str, np.ndarray]:
    """Two 40x30 RGB images (a smooth scene and a noisy, shifted, dimmed copy) and a mask, as f32,
    with the metrics of the f32 values, masked and not."""
    rng = np.random.default_rng(seed)
    h, w = 30, 40
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    a = np.stack([0.5 + 0.4 * np.sin(6 * xx + 2 * yy), yy, 0.3 + 0.5 * xx * yy], -1)
    b = 0.9 * np.roll(a, 1, axis=1) + rng.normal(0, 0.05, a.shape)
    a, b = a.astype(np.float32), np.clip(b, 0, 1).astype(np.float32)
    mask = np.zeros((h, w), bool)
    mask[5:25, 8:30] = True
    mask[12, :] = True
    return {
        "a": a,
        "b": b,
        "mask": mask.astype(np.uint8),
        "psnr": np.array([psnr(a, b)]),
        "psnr_masked": np.array([psnr(a, b, mask)]),
        "ssim": np.array([ssim(a, b)]),
        "ssim_masked": np.array([ssim(a, b, mask)]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("models/fixtures/metrics"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    t = cases()
    save_file(t, str(args.out / "cases.safetensors"), metadata={"generator": "python -m c4g.raster.metrics"})
    print({k: float(v[0]) for k, v in t.items() if v.size == 1})


if __name__ == "__main__":
    main()
