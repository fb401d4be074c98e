"""The float64 gradient reference: PyTorch autograd through a dense implementation of the forward model
(renderer/src/raster/mod.rs, both footprints), what the renderer crate's backward pass is held to.

Written apart from the Rust code and from `dense` (which is the training rasterizer): every Gaussian is
evaluated at every pixel of a chunk of pixels, the cuts (the footprint's edge, the 1/255 skip, the
transmittance stop, near and far) are masks computed without gradient from the same float64 values, and
everything else is autograd. That is the convention the Rust backward states (`raster::grad`): a render is
piecewise smooth and its gradient is the gradient of the piece the forward pass took; through the alpha
clamp at 0.99 the gradient is zero (autograd's `clamp_max`).

Gradients are returned in the optimiser's parametrisation: position, log scale (`s · ∂L/∂s`), the stored
unnormalised quaternion (through the normalisation), opacity logit (`o(1 − o) · ∂L/∂o`), colour, the
projected centre in pixels, and the camera's `[ωx, ωy, ωz, νx, νy, νz, log focal]` (a left increment of
world-to-camera and a focal scale shared by fx and fy). Autograd runs on the activated values and the
elementwise activations are applied by the chain rule, so a zero scale or an opacity of exactly 1 (whose
log or logit is infinite) still has its gradient.

The loss the fixtures use is linear in the render, `L = Σ w·rgb + Σ wa·alpha + Σ we·expected depth`, with
weights from `upstream_weights` (an integer hash both languages compute exactly), so its gradient with
respect to the render is the weights themselves.

    cd models/python && python -m c4g.raster.grad_reference --scenes ../fixtures/scenes --out ../fixtures/gradients
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from .reference import ALPHA_MAX, ALPHA_MIN, EPS2D, FAR, FOV_CLAMP, NEAR, SIGMA_EXTENT, T_MIN, TILE_3DGS, Camera, tiles_3dgs

#: The scale of the expected-depth weights: depth is in scene units, several times a colour.
DEPTH_WEIGHT = 0.1
#: Pixels evaluated at once (memory: about 20 float64 [N, CHUNK] tensors kept for autograd).
CHUNK = 2048


def upstream_weights(pixels: int, seed: int) -> dict[str, np.ndarray]:
    """The fixtures' loss weights: `rgb` [3·pixels], `alpha` and `expected_depth` [pixels], float32.
    Weight k of a plane is `2·frac((k·0x9E3779B1 + seed + plane) / 2³²) − 1` (rgb plane 0, alpha 1,
    expected depth 2; expected depth times DEPTH_WEIGHT), rounded to float32: exact integer arithmetic,
    the same in Rust (renderer/tests/gradient_reference.rs)."""

    def plane(n: int, p: int) -> np.ndarray:
        k = np.arange(n, dtype=np.uint64)
        h = (k * np.uint64(0x9E3779B1) + np.uint64(seed + p)) % np.uint64(2**32)
        return (2.0 * (h.astype(np.float64) / 2.0**32) - 1.0).astype(np.float32)

    return {
        "rgb": plane(3 * pixels, 0),
        "alpha": plane(pixels, 1),
        "expected_depth": (plane(pixels, 2).astype(np.float64) * DEPTH_WEIGHT).astype(np.float32),
    }


def _skew(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros((), dtype=w.dtype)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]), torch.stack([-w[1], w[0], z])])


def _rotation(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ]
    return torch.stack(rows, -2)


def gradients(
    means: np.ndarray,
    scales: np.ndarray,
    rotations_wxyz: np.ndarray,
    opacities: np.ndarray,
    colors: np.ndarray,
    cam: Camera,
    weights: dict[str, np.ndarray],
    background=(0.0, 0.0, 0.0),
    footprint: str = "ellipse",
    near: float = NEAR,
    far: float = FAR,
    dtype: torch.dtype = torch.float64,
) -> dict[str, np.ndarray]:
    """The render (rgb [H·W·3], alpha, expected_depth [H·W]) and the gradient of
    `Σ weights["rgb"]·rgb + Σ weights["alpha"]·alpha + Σ weights["expected_depth"]·expected depth` with
    respect to every Gaussian (positions, log_scales, rotations, opacity_logits, colors, means2d) and the
    camera ([7]). Every parameter must be finite (the Rust API refuses others). `dtype` float32 is for
    timing only (the benchmark baseline), never for reference values."""
    t = lambda a: torch.tensor(np.asarray(a, dtype=np.float64), dtype=dtype)  # noqa: E731
    n = len(opacities)
    leaves = {
        "positions": t(means).reshape(n, 3),
        "scales": t(scales).reshape(n, 3),
        "rotations": t(rotations_wxyz).reshape(n, 4),
        "opacities": t(opacities).reshape(n),
        "colors": t(colors).reshape(n, 3),
        "camera": torch.zeros(7, dtype=dtype),
    }
    for v in leaves.values():
        v.requires_grad_(True)
    if not all(bool(torch.isfinite(v).all()) for v in leaves.values()):
        raise ValueError("every parameter must be finite")
    view = t(cam.world_to_camera)
    increment = torch.eye(3, dtype=dtype) + _skew(leaves["camera"][:3])  # exp(ω^) to first order: exact at 0
    rot_w = increment @ view[:3, :3]
    t_w = increment @ view[:3, 3] + leaves["camera"][3:6]
    focal = torch.exp(leaves["camera"][6])
    fx, fy = cam.fx * focal, cam.fy * focal

    p = leaves["positions"] @ rot_w.T + t_w
    x, y, z = p.unbind(-1)
    qn = leaves["rotations"].norm(dim=-1)
    with torch.no_grad():
        keep = (z >= near) & (z <= far) & (leaves["opacities"] >= ALPHA_MIN) & (qn > 0)
    idx = torch.nonzero(keep).flatten()
    # Invalid ones are dropped before any arithmetic that could be NaN.
    x, y, z = x[idx], y[idx], z[idx]
    lim_x, lim_y = FOV_CLAMP * cam.width / (2 * fx), FOV_CLAMP * cam.height / (2 * fy)
    tx = torch.maximum(torch.minimum(x / z, lim_x), -lim_x) * z
    ty = torch.maximum(torch.minimum(y / z, lim_y), -lim_y) * z
    zero = torch.zeros_like(z)
    jac = torch.stack([torch.stack([fx / z, zero, -fx * tx / z**2], -1), torch.stack([zero, fy / z, -fy * ty / z**2], -1)], -2)
    m = jac @ rot_w @ _rotation(leaves["rotations"][idx]) * leaves["scales"][idx][:, None, :]
    cov = m @ m.transpose(-1, -2)
    a, b, c = cov[:, 0, 0] + EPS2D, cov[:, 0, 1], cov[:, 1, 1] + EPS2D
    det = a * c - b * b
    u = fx * x / z + cam.cx
    v = fy * y / z + cam.cy
    uv = torch.stack([u, v], -1)
    uv.retain_grad()
    with torch.no_grad():
        ok = det > 0
        # Front to back: depth, ties by index (the Rust order breaks ties of its float32 depth by index;
        # the fixture scenes keep overlapping depths apart).
        order = sorted((i for i in range(len(idx)) if ok[i]), key=lambda i: (float(z[i]), int(idx[i])))
    order = torch.tensor(order, dtype=torch.long)
    conic = torch.stack([c, -b, a], -1)[order] / det[order, None]
    opac = leaves["opacities"][idx][order]
    col = leaves["colors"][idx][order]
    zs, us, vs = z[order], uv[order, 0], uv[order, 1]
    if footprint == "3dgs":
        cov_np = cov.detach().numpy()
        uv_np = uv.detach().numpy()
        boxes = []
        for i in order.tolist():
            _, (x0, y0, x1, y1) = tiles_3dgs(uv_np[i], cov_np[i] + EPS2D * np.eye(2), cam.width, cam.height)
            boxes.append((x0 * TILE_3DGS, y0 * TILE_3DGS, x1 * TILE_3DGS, y1 * TILE_3DGS))
        boxes = torch.tensor(boxes, dtype=dtype).reshape(-1, 4)
    elif footprint != "ellipse":
        raise ValueError(f"unknown footprint {footprint!r}")

    h, w = cam.height, cam.width
    bg = t(background)
    wts = {k: t(v) for k, v in weights.items()}
    rgb_out, alpha_out, depth_out = [], [], []
    for start in range(0, h * w, CHUNK):
        pix = torch.arange(start, min(start + CHUNK, h * w))
        px, py = (pix % w).to(dtype), (pix // w).to(dtype)
        dx, dy = px[None, :] + 0.5 - us[:, None], py[None, :] + 0.5 - vs[:, None]
        d2 = conic[:, 0:1] * dx * dx + 2 * conic[:, 1:2] * dx * dy + conic[:, 2:3] * dy * dy
        alpha = torch.clamp_max(opac[:, None] * torch.exp(-0.5 * d2), ALPHA_MAX)
        with torch.no_grad():
            if footprint == "ellipse":
                inside = d2 <= SIGMA_EXTENT**2
            else:
                inside = (px[None, :] >= boxes[:, 0:1]) & (px[None, :] < boxes[:, 2:3]) & (py[None, :] >= boxes[:, 1:2]) & (py[None, :] < boxes[:, 3:4]) & (d2 >= 0)
            hit = inside & (alpha >= ALPHA_MIN)
            after = torch.cumprod(1 - torch.where(hit, alpha, 0.0), dim=0)
            hit &= after >= T_MIN  # the stop: that Gaussian and all behind it (T only falls)
        alpha = torch.where(hit, alpha, torch.zeros_like(alpha))
        t_after = torch.cumprod(1 - alpha, dim=0)
        t_before = torch.cat([torch.ones_like(t_after[:1]), t_after[:-1]], 0)
        weight = alpha * t_before
        final_t = t_after[-1] if len(order) else torch.ones(len(pix), dtype=dtype)
        rgb = weight.T @ col + final_t[:, None] * bg
        alpha_img = 1 - final_t
        depth = weight.T @ zs
        expected = torch.where(alpha_img > 0, depth / torch.where(alpha_img > 0, alpha_img, torch.ones_like(alpha_img)), 0.0)
        loss = (wts["rgb"][3 * start : 3 * start + 3 * len(pix)] * rgb.reshape(-1)).sum()
        loss = loss + (wts["alpha"][pix] * alpha_img).sum() + (wts["expected_depth"][pix] * expected).sum()
        loss.backward(retain_graph=True)
        rgb_out.append(rgb.detach().reshape(-1))
        alpha_out.append(alpha_img.detach())
        depth_out.append(expected.detach())

    g = {k: (v.grad if v.grad is not None else torch.zeros_like(v)).numpy() for k, v in leaves.items()}
    s = leaves["scales"].detach().numpy()
    o = leaves["opacities"].detach().numpy()
    means2d = np.zeros((n, 2))
    if uv.grad is not None:
        means2d[idx.numpy()] = uv.grad.numpy()
    return {
        "rgb": torch.cat(rgb_out).numpy().astype(np.float64),
        "alpha": torch.cat(alpha_out).numpy().astype(np.float64),
        "expected_depth": torch.cat(depth_out).numpy().astype(np.float64),
        "positions": g["positions"],
        "log_scales": g["scales"] * s,
        "rotations": g["rotations"],
        "opacity_logits": g["opacities"] * o * (1 - o),
        "colors": g["colors"],
        "means2d": means2d,
        "camera": g["camera"],
    }


def scene_gradients(path: Path, seed: int = 0) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The gradients of the fixture scene at `path` (models/fixtures/scenes/) under the
    `upstream_weights(pixels, seed)` loss, its Gaussians with a non-finite parameter or feature left out
    (`kept`: the indices of the others; the forward model skips those, the Rust differentiable render
    refuses them)."""
    from safetensors import safe_open

    with safe_open(str(path), framework="np") as f:
        sc = {k: f.get_tensor(k) for k in f.keys()}
        meta = f.metadata() or {}
    footprint = meta.get("footprint", "ellipse")
    width, height = (int(v) for v in sc["size"])
    fx, fy, cx, cy = (float(v) for v in sc["intrinsics"])
    cam = Camera(fx, fy, cx, cy, width, height, sc["world_to_camera"].astype(np.float64))
    params = [sc[k].astype(np.float64) for k in ("positions", "scales", "rotations", "opacities", "colors")]
    n = len(params[3])
    finite = np.ones(n, dtype=bool)
    # A non-finite feature vector makes the forward model skip its Gaussian too.
    for p in params + ([sc["features"]] if "features" in sc else []):
        finite &= np.isfinite(p.reshape(n, -1)).all(axis=1)
    kept = np.nonzero(finite)[0]
    weights = upstream_weights(width * height, seed)
    out = gradients(*(p[kept] for p in params), cam, weights, background=tuple(sc["background"].astype(np.float64)), footprint=footprint)
    out["kept"] = kept.astype(np.int32)
    return out, {"footprint": footprint, "seed": str(seed), "scene": path.stem}


def bench(n: int, size: int, footprint: str, dtype: torch.dtype) -> float:
    """Seconds for one forward + backward of `gradients` on `n` random Gaussians at `size`²: the dense
    autograd baseline of renderer/benches/gradients.rs (its scene's distribution: a frustum slab at depth
    2..6 before C4G's default intrinsics, σ about 1.5 pixels at 256²)."""
    import time

    rng = np.random.default_rng(n)
    tan = 0.5 / 0.8767
    z = rng.uniform(2, 6, n)
    means = np.stack([rng.uniform(-1, 1, n) * tan * z, rng.uniform(-1, 1, n) * tan * z, z], -1)
    scales = 0.027 * rng.uniform(0.4, 1.6, (n, 3))
    rots = rng.uniform(-0.5, 0.5, (n, 4))
    cam = Camera(0.8767 * size, 0.8767 * size, size / 2, size / 2, size, size, np.eye(4))
    weights = upstream_weights(size * size, 0)
    start = time.perf_counter()
    gradients(means, scales, rots, rng.uniform(0.1, 1, n), rng.uniform(0, 1, (n, 3)), cam, weights, footprint=footprint, dtype=dtype)
    return time.perf_counter() - start


def main() -> None:
    from safetensors.numpy import save_file

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=Path, help="models/fixtures/scenes")
    ap.add_argument("--out", type=Path, help="models/fixtures/gradients")
    ap.add_argument("--only", nargs="*", help="scene file stems (default: all)")
    ap.add_argument("--bench", nargs=2, type=int, metavar=("N", "SIZE"), help="time one float32 forward + backward instead")
    ap.add_argument("--footprint", default="ellipse", help="with --bench")
    args = ap.parse_args()
    if args.bench:
        seconds = bench(*args.bench, args.footprint, torch.float32)
        print(f"seconds {seconds:.4f} threads {torch.get_num_threads()}")
        return
    if args.scenes is None or args.out is None:
        ap.error("--scenes and --out are required")
    args.out.mkdir(parents=True, exist_ok=True)
    for path in sorted(args.scenes.glob("*.safetensors")):
        if args.only and path.stem not in args.only:
            continue
        out, meta = scene_gradients(path)
        # The render is only a check on this module (against `reference`); the gradients are the fixture.
        tensors = {k: np.ascontiguousarray(v) for k, v in out.items() if k not in ("rgb", "alpha", "expected_depth")}
        save_file(tensors, str(args.out / f"{path.stem}.safetensors"), metadata=meta)
        print(path.stem, {k: v.shape for k, v in tensors.items()})


if __name__ == "__main__":
    main()
