"""A differentiable PyTorch rasterizer of the same forward model as `reference` and the
renderer crate (renderer/src/raster/mod.rs), for training and for making data.

Dense rather than tiled: every Gaussian is evaluated at every pixel, [N, H·W] at once. That is the
right shape for the small images and ~2K Gaussians of training on a CPU, and it makes the early stop
exact without a loop: transmittance only falls along the depth order, so "stop before the Gaussian
that would bring T below 1e-4" is the mask T_after >= 1e-4 on the cumulative product.
"""

from __future__ import annotations

import torch

from .reference import ALPHA_MAX, ALPHA_MIN, EPS2D, FAR, FOV_CLAMP, NEAR, SIGMA_EXTENT, T_MIN


def quat_wxyz_to_matrix(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip


def render(
    means: torch.Tensor,
    scales: torch.Tensor,
    rotations_wxyz: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    intrinsics: tuple[float, float, float, float],
    world_to_camera: torch.Tensor,
    width: int,
    height: int,
    features: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    near: float = NEAR,
    far: float = FAR,
    weights: bool = False,
) -> dict[str, torch.Tensor]:
    """Renders N Gaussians ([N, 3] means and linear scales, [N, 4] w-x-y-z rotations, [N] opacities,
    [N, 3] colours, optional [N, F] features) with pinhole `intrinsics` (fx, fy, cx, cy in pixels)
    and a [4, 4] world-to-camera pose. Returns rgb [H, W, 3], alpha, depth (alpha-weighted),
    expected_depth [H, W] and features [H, W, F]; with `weights`, also each Gaussian's blending
    weight at each pixel, "weights" [N, H·W] in the Gaussians' own order (what a per-Gaussian
    quantity is composited with)."""
    fx, fy, cx, cy = intrinsics
    dtype = means.dtype
    params = [means, scales, rotations_wxyz, opacities[:, None], colors] + ([features] if features is not None else [])
    valid = torch.isfinite(torch.cat(params, dim=1)).all(dim=1) & (rotations_wxyz.norm(dim=-1) > 0)
    fill = lambda a, v: torch.where(valid[:, None], a, torch.full_like(a, v))  # noqa: E731
    # Invalid Gaussians get harmless values: their weight is zero, but 0 · NaN would still poison.
    means, scales, rots = fill(means, 0.0), fill(scales, 0.0), fill(rotations_wxyz, 1.0)
    opacities, colors = fill(opacities[:, None], 0.0)[:, 0], fill(colors, 0.0)
    features = fill(features, 0.0) if features is not None else None

    rot_w, t_w = world_to_camera[:3, :3].to(dtype), world_to_camera[:3, 3].to(dtype)
    p = means @ rot_w.T + t_w
    x, y, z = p.unbind(-1)
    valid = valid & (z >= near) & (z <= far)
    z_safe = torch.where(valid, z, torch.ones_like(z))
    lim_x, lim_y = FOV_CLAMP * 0.5 * width / fx, FOV_CLAMP * 0.5 * height / fy
    tx = (x / z_safe).clamp(-lim_x, lim_x) * z_safe
    ty = (y / z_safe).clamp(-lim_y, lim_y) * z_safe
    zero = torch.zeros_like(z_safe)
    jac = torch.stack(
        [fx / z_safe, zero, -fx * tx / z_safe**2, zero, fy / z_safe, -fy * ty / z_safe**2], -1
    ).reshape(-1, 2, 3)
    m = jac @ rot_w @ quat_wxyz_to_matrix(rots) * scales[:, None, :]
    cov = m @ m.transpose(-1, -2)
    a, b, c = cov[:, 0, 0] + EPS2D, cov[:, 0, 1], cov[:, 1, 1] + EPS2D
    det = a * c - b * b
    valid = valid & (det > 0)
    det = torch.where(valid, det, torch.ones_like(det))
    u, v = fx * x / z_safe + cx, fy * y / z_safe + cy

    # Front to back; invalid Gaussians last (their alpha is zero anyway). Stable: ties by index.
    order = torch.sort(torch.where(valid, z, torch.full_like(z, float("inf"))), stable=True).indices
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=means.device) + 0.5,
        torch.arange(width, dtype=dtype, device=means.device) + 0.5,
        indexing="ij",
    )
    px, py = xs.reshape(1, -1), ys.reshape(1, -1)
    o = order
    dx, dy = px - u[o, None], py - v[o, None]
    d2 = (c[o, None] * dx * dx - 2 * b[o, None] * dx * dy + a[o, None] * dy * dy) / det[o, None]
    alpha = torch.clamp_max(opacities[o, None].to(dtype) * torch.exp(-0.5 * d2), ALPHA_MAX)
    alpha = torch.where((d2 <= SIGMA_EXTENT**2) & (alpha >= ALPHA_MIN) & valid[o, None], alpha, torch.zeros_like(alpha))
    after = torch.cumprod(1 - alpha, dim=0)
    alpha = torch.where(after >= T_MIN, alpha, torch.zeros_like(alpha))
    trans_after = torch.cumprod(1 - alpha, dim=0)
    trans_before = torch.cat((torch.ones_like(trans_after[:1]), trans_after[:-1]), dim=0)
    weight = alpha * trans_before  # [N, HW]

    final_t = trans_after[-1] if len(o) else torch.ones(height * width, dtype=dtype, device=means.device)
    rgb = weight.T @ colors[o].to(dtype)
    if background is not None:
        rgb = rgb + final_t[:, None] * background.to(dtype)
    depth = weight.T @ z_safe[o]
    alpha_img = 1 - final_t
    expected = torch.where(alpha_img > 0, depth / torch.where(alpha_img > 0, alpha_img, torch.ones_like(alpha_img)), 0.0)
    out = {
        "rgb": rgb.reshape(height, width, 3),
        "alpha": alpha_img.reshape(height, width),
        "depth": depth.reshape(height, width),
        "expected_depth": expected.reshape(height, width),
    }
    if features is not None:
        out["features"] = (weight.T @ features[o].to(dtype)).reshape(height, width, -1)
    if weights:
        out["weights"] = torch.zeros_like(weight).index_copy(0, o, weight)
    return out


def render_batch(
    means: torch.Tensor,
    scales: torch.Tensor,
    rotations_wxyz: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    intrinsics: tuple[float, float, float, float],
    world_to_camera: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """`fast.render_batch`'s contract ([B, N, ·] sets, [B, 4, 4] poses → rgb [B, H, W, 3],
    alpha, depth, expected_depth [B, H, W]) on this dense rasterizer, one set at a time: the path for
    tensors on a GPU, where the Numba kernels cannot run and [N, H·W] at once is cheap. Gradients
    come from autograd through the same forward model; the cuts are constants here as there."""
    renders = [
        render(
            means[b], scales[b], rotations_wxyz[b], opacities[b], colors[b], intrinsics, world_to_camera[b], width, height,
            background=None if background is None else background[b],
        )
        for b in range(means.shape[0])
    ]  # fmt: skip
    return {key: torch.stack([r[key] for r in renders]) for key in ("rgb", "alpha", "depth", "expected_depth")}
