"""A fast, differentiable rasterizer of the same forward model as `reference`, for making
data, training and evaluating on a CPU.

`dense` evaluates every Gaussian at every pixel: exact, but on a 2-core machine a 64 x 64
frame of 1K Gaussians takes a third of a second. Here the 3D → 2D projection stays in PyTorch (cheap,
[N]-sized, differentiated by autograd), and the per-pixel blend — the expensive part — runs in a
Numba kernel over 16 x 16 tiles with a hand-written backward pass, as in 3DGS:

- forward, front to back, with every rule of the forward model (3-sigma cut, alpha clamp 0.99, skip
  alpha < 1/255, stop before transmittance would fall below 1e-4);
- backward, back to front per pixel, recovering each transmittance by division (alpha <= 0.99, so
  1 - alpha >= 0.01) and the colour behind it from running sums.

Gradients flow to the 2D centres, conics, opacities, colours and depths, and from there through the
projection to the 3D parameters. The cuts themselves are treated as constants (they are steps).

Footprint: the ellipse only (`reference` footprint "ellipse", `Footprint::Ellipse` in the renderer
crate): a Gaussian reaches the pixels within 3 sigma, not every pixel of its 3DGS tiles. This is the rule
c4g-tiny was trained with (its model.json declares `"rasterizer": {"footprint": "ellipse"}`); the official
C4G weights were trained with the original 3DGS rasterizer's tiles ("3dgs"), which this module does not
implement.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from .dense import quat_wxyz_to_matrix
from .reference import ALPHA_MAX, ALPHA_MIN, EPS2D, FAR, FOV_CLAMP, NEAR, SIGMA_EXTENT, T_MIN

TILE = 16
D2_MAX = SIGMA_EXTENT**2


def project(means, scales, rotations_wxyz, world_to_camera, intrinsics, width, height, near=NEAR, far=FAR):
    """[B, N, ...] Gaussians and [B, 4, 4] poses → pixel centres [B, N, 2], conics (A, B, C) of
    d² = A dx² + 2B dx dy + C dy² [B, N, 3], depths [B, N], 3-sigma radii [B, N] (no gradient) and a
    validity mask [B, N]. Written with the same operations as `reference.project`."""
    fx, fy, cx, cy = intrinsics
    rot_w, t_w = world_to_camera[:, None, :3, :3], world_to_camera[:, None, :3, 3]
    p = (rot_w @ means[..., None])[..., 0] + t_w
    x, y, z = p.unbind(-1)
    finite = torch.isfinite(torch.cat((means, scales, rotations_wxyz), -1)).all(-1) & (rotations_wxyz.norm(dim=-1) > 0)
    valid = finite & (z >= near) & (z <= far)
    z_safe = torch.where(valid, z, torch.ones_like(z))
    lim_x, lim_y = FOV_CLAMP * 0.5 * width / fx, FOV_CLAMP * 0.5 * height / fy
    tx = (x / z_safe).clamp(-lim_x, lim_x) * z_safe
    ty = (y / z_safe).clamp(-lim_y, lim_y) * z_safe
    zero = torch.zeros_like(z_safe)
    jac = torch.stack([fx / z_safe, zero, -fx * tx / z_safe**2, zero, fy / z_safe, -fy * ty / z_safe**2], -1)
    jac = jac.reshape(*z.shape, 2, 3)
    rots = torch.where(finite[..., None], rotations_wxyz, torch.ones_like(rotations_wxyz))
    m = jac @ rot_w @ quat_wxyz_to_matrix(rots) * scales[..., None, :]
    cov = m @ m.transpose(-1, -2)
    a, b, c = cov[..., 0, 0] + EPS2D, cov[..., 0, 1], cov[..., 1, 1] + EPS2D
    det = a * c - b * b
    valid = valid & (det > 0)
    det = torch.where(valid, det, torch.ones_like(det))
    conic = torch.stack((c / det, -b / det, a / det), -1)
    uv = torch.stack((fx * x / z_safe + cx, fy * y / z_safe + cy), -1)
    with torch.no_grad():
        # 3 sigma along the major axis of the covariance: every pixel with d² <= 9 lies within it.
        mid, disc = 0.5 * (a + c), torch.sqrt(torch.clamp_min(0.25 * (a - c) ** 2 + b * b, 0.0))
        radius = torch.where(valid, SIGMA_EXTENT * torch.sqrt(mid + disc), torch.zeros_like(mid))
    return uv, conic, z_safe, radius, valid


@numba.njit(cache=True)
def _tile_lists(uv, radius, order, valid, width, height):
    """Per tile, the Gaussians whose 3-sigma box touches it, front to back (CSR: offsets, indices)."""
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    counts = np.zeros(tiles_x * tiles_y, np.int64)
    boxes = np.zeros((len(order), 4), np.int64)
    for i in order:
        if not valid[i]:
            boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3] = 0, -1, 0, -1
            continue
        u, v, r = uv[i, 0], uv[i, 1], radius[i]
        # Clamped in floating point first: a Gaussian far off-screen has |u| beyond any integer.
        x0 = int(min(max(np.floor((u - r) / TILE), 0.0), tiles_x))
        x1 = int(min(max(np.floor((u + r) / TILE), -1.0), tiles_x - 1))
        y0 = int(min(max(np.floor((v - r) / TILE), 0.0), tiles_y))
        y1 = int(min(max(np.floor((v + r) / TILE), -1.0), tiles_y - 1))
        boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3] = x0, x1, y0, y1
        for ty in range(y0, y1 + 1):
            for tx in range(x0, x1 + 1):
                counts[ty * tiles_x + tx] += 1
    offsets = np.zeros(len(counts) + 1, np.int64)
    offsets[1:] = np.cumsum(counts)
    fill = offsets[:-1].copy()
    indices = np.zeros(offsets[-1], np.int64)
    for i in order:
        x0, x1, y0, y1 = boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3]
        for ty in range(y0, y1 + 1):
            for tx in range(x0, x1 + 1):
                t = ty * tiles_x + tx
                indices[fill[t]] = i
                fill[t] += 1
    return offsets, indices, tiles_x


@numba.njit(cache=True)
def _alpha(conic, uv, opac, i, px, py):
    dx, dy = px - uv[i, 0], py - uv[i, 1]
    d2 = conic[i, 0] * dx * dx + 2.0 * conic[i, 1] * dx * dy + conic[i, 2] * dy * dy
    raw = opac[i] * np.exp(-0.5 * d2)
    return d2, raw, min(ALPHA_MAX, raw), dx, dy


@numba.njit(cache=True, parallel=True)
def _forward(uv, conic, opac, colors, z, radius, valid, order, background, width, height):
    b_count = uv.shape[0]
    rgb = np.zeros((b_count, height, width, 3))
    depth = np.zeros((b_count, height, width))
    trans = np.ones((b_count, height, width))
    ends = np.zeros((b_count, height, width), np.int64)  # list position after the last Gaussian visited
    for b in numba.prange(b_count):
        offsets, indices, tiles_x = _tile_lists(uv[b], radius[b], order[b], valid[b], width, height)
        for py_i in range(height):
            for px_i in range(width):
                t = (py_i // TILE) * tiles_x + px_i // TILE
                px, py = px_i + 0.5, py_i + 0.5
                tr, r, g, bl, d = 1.0, 0.0, 0.0, 0.0, 0.0
                k = offsets[t]
                while k < offsets[t + 1]:
                    i = indices[k]
                    d2, raw, alpha, _, _ = _alpha(conic[b], uv[b], opac[b], i, px, py)
                    if d2 <= D2_MAX and alpha >= ALPHA_MIN:
                        nxt = tr * (1.0 - alpha)
                        if nxt < T_MIN:
                            break
                        w = alpha * tr
                        r += w * colors[b, i, 0]
                        g += w * colors[b, i, 1]
                        bl += w * colors[b, i, 2]
                        d += w * z[b, i]
                        tr = nxt
                    k += 1
                ends[b, py_i, px_i] = k
                rgb[b, py_i, px_i, 0] = r + tr * background[b, 0]
                rgb[b, py_i, px_i, 1] = g + tr * background[b, 1]
                rgb[b, py_i, px_i, 2] = bl + tr * background[b, 2]
                depth[b, py_i, px_i] = d
                trans[b, py_i, px_i] = tr
    return rgb, depth, trans, ends


@numba.njit(cache=True, parallel=True)
def _backward(uv, conic, opac, colors, z, radius, valid, order, background, width, height, trans, ends, g_rgb, g_depth, g_alpha):
    b_count, n = uv.shape[0], uv.shape[1]
    d_uv = np.zeros_like(uv)
    d_conic = np.zeros_like(conic)
    d_opac = np.zeros_like(opac)
    d_colors = np.zeros_like(colors)
    d_z = np.zeros_like(z)
    for b in numba.prange(b_count):
        offsets, indices, tiles_x = _tile_lists(uv[b], radius[b], order[b], valid[b], width, height)
        for py_i in range(height):
            for px_i in range(width):
                t = (py_i // TILE) * tiles_x + px_i // TILE
                px, py = px_i + 0.5, py_i + 0.5
                gr, gg, gb = g_rgb[b, py_i, px_i, 0], g_rgb[b, py_i, px_i, 1], g_rgb[b, py_i, px_i, 2]
                gd, ga = g_depth[b, py_i, px_i], g_alpha[b, py_i, px_i]
                t_final = trans[b, py_i, px_i]
                # dL/dT_final: the background term, and alpha = 1 - T_final.
                g_tfinal = gr * background[b, 0] + gg * background[b, 1] + gb * background[b, 2] - ga
                tr_after = t_final
                behind = 0.0  # sum over Gaussians behind of w_j (c_j . gC + z_j gD)
                k = ends[b, py_i, px_i] - 1
                while k >= offsets[t]:
                    i = indices[k]
                    d2, raw, alpha, dx, dy = _alpha(conic[b], uv[b], opac[b], i, px, py)
                    if d2 <= D2_MAX and alpha >= ALPHA_MIN:
                        one_minus = 1.0 - alpha
                        tr_before = tr_after / one_minus
                        w = alpha * tr_before
                        own = colors[b, i, 0] * gr + colors[b, i, 1] * gg + colors[b, i, 2] * gb + z[b, i] * gd
                        d_colors[b, i, 0] += w * gr
                        d_colors[b, i, 1] += w * gg
                        d_colors[b, i, 2] += w * gb
                        d_z[b, i] += w * gd
                        d_alpha = tr_before * own - (behind + t_final * g_tfinal) / one_minus
                        behind += w * own
                        tr_after = tr_before
                        if raw < ALPHA_MAX:
                            gauss = raw / opac[b, i]
                            d_opac[b, i] += d_alpha * gauss
                            d_d2 = -0.5 * raw * d_alpha
                            d_conic[b, i, 0] += d_d2 * dx * dx
                            d_conic[b, i, 1] += d_d2 * 2.0 * dx * dy
                            d_conic[b, i, 2] += d_d2 * dy * dy
                            d_uv[b, i, 0] -= d_d2 * 2.0 * (conic[b, i, 0] * dx + conic[b, i, 1] * dy)
                            d_uv[b, i, 1] -= d_d2 * 2.0 * (conic[b, i, 1] * dx + conic[b, i, 2] * dy)
                    k -= 1
    return d_uv, d_conic, d_opac, d_colors, d_z


class _Blend(torch.autograd.Function):
    @staticmethod
    def forward(ctx, uv, conic, opac, colors, z, radius, valid, background, width, height):
        np64 = lambda a: a.detach().to(torch.float64).contiguous().numpy()  # noqa: E731
        order = torch.argsort(torch.where(valid, z, torch.full_like(z, float("inf"))), dim=-1, stable=True)
        opac_eff = torch.where(valid, opac, torch.zeros_like(opac))
        args = (
            np64(uv), np64(conic), np64(opac_eff), np64(colors), np64(z), np64(radius),
            valid.numpy(), order.numpy(), np64(background), width, height,
        )  # fmt: skip
        rgb, depth, trans, ends = _forward(*args)
        ctx.args, ctx.trans, ctx.ends, ctx.dtype = args, trans, ends, uv.dtype
        ctx.valid = valid
        to = lambda a: torch.from_numpy(a).to(uv.dtype)  # noqa: E731
        return to(rgb), to(depth), to(1.0 - trans)

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_alpha):
        np64 = lambda a: a.detach().to(torch.float64).contiguous().numpy()  # noqa: E731
        grads = _backward(*ctx.args, ctx.trans, ctx.ends, np64(g_rgb), np64(g_depth), np64(g_alpha))
        d_uv, d_conic, d_opac, d_colors, d_z = (torch.from_numpy(g).to(ctx.dtype) for g in grads)
        d_opac = torch.where(ctx.valid, d_opac, torch.zeros_like(d_opac))
        return d_uv, d_conic, d_opac, d_colors, d_z, None, None, None, None, None


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
    """Renders B sets of N Gaussians ([B, N, 3] means and linear scales, [B, N, 4] w-x-y-z rotations,
    [B, N] opacities, [B, N, 3] colours) with pinhole intrinsics in pixels and [B, 4, 4]
    world-to-camera poses. Returns rgb [B, H, W, 3], alpha, depth (alpha-weighted) and
    expected_depth [B, H, W]; differentiable in every Gaussian parameter."""
    uv, conic, z, radius, valid = project(means, scales, rotations_wxyz, world_to_camera, intrinsics, width, height)
    finite = torch.isfinite(torch.cat((opacities[..., None], colors), -1)).all(-1)
    valid = valid & finite
    colors = torch.where(valid[..., None], colors, torch.zeros_like(colors))
    if background is None:
        background = torch.zeros(means.shape[0], 3, dtype=means.dtype)
    rgb, depth, alpha = _Blend.apply(uv, conic, opacities, colors, z, radius, valid, background, width, height)
    expected = torch.where(alpha > 0, depth / torch.where(alpha > 0, alpha, torch.ones_like(alpha)), torch.zeros_like(depth))
    return {"rgb": rgb, "alpha": alpha, "depth": depth, "expected_depth": expected}


def dominant_ids(gaussians: tuple, ids: np.ndarray, intrinsics: tuple, w2c: np.ndarray, size: int) -> np.ndarray:
    """Per-pixel object ids [T, H, W] (uint8) of T sets of Gaussians (means, linear scales, w-x-y-z
    rotations, opacities; [T, N, ·] float64) whose Gaussian i belongs to object `ids[i]`: the id
    that carries most of each pixel's blending weight. Each id's one-hot indicator is composited as
    a colour channel, three ids a render."""
    args = tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in gaussians)
    count = int(ids.max()) + 1
    one_hot = np.eye(3 * -(-count // 3))[ids]  # [N, ids rounded up to a multiple of 3]
    weights = []
    with torch.no_grad():
        for first in range(0, one_hot.shape[1], 3):
            channels = torch.from_numpy(np.broadcast_to(one_hot[None, :, first : first + 3], (len(w2c), len(ids), 3)).copy())
            weights.append(render_batch(*args, channels, intrinsics, torch.from_numpy(w2c), size, size)["rgb"])
    return torch.cat(weights, dim=-1)[..., :count].argmax(dim=-1).numpy().astype(np.uint8)
