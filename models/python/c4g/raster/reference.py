"""A float64 reference of the 3D Gaussian splatting forward model, written for clarity, not speed.

The renderer crate's CPU and wgpu rasterizers are held against it. Constants are those of the
3DGS convention (docs: ../shared/docs/C4G_MODEL.md, "Rasterisation constants"):

- camera: pinhole, OpenCV (x right, y down, z forward), world-to-camera [R | t]; pixel (i, j) has
  its centre at (i + 0.5, j + 0.5) in the coordinates of cx, cy (so cx = W / 2 is the image centre);
- Gaussians whose camera-space depth is outside [near, far], or with any non-finite parameter, are
  skipped;
- EWA projection: J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] with x/z and y/z clamped to
  1.3 x the half-FOV tangent (W / (2 fx), H / (2 fy)); Σ2D = J W Σ Wᵀ Jᵀ + 0.3 I;
- which pixels a Gaussian is evaluated at is its footprint (`renderer/src/raster/mod.rs` states both
  rules and every difference from 3DGS):
  - "ellipse" (the default): the pixels within 3 sigma, Mahalanobis distance (under Σ2D) at most 3;
  - "3dgs", the original 3DGS CUDA rasterizer's rule: every pixel of the 16 x 16 tiles
    [floor((p - r) / 16), floor((p + r + 15) / 16)) (clamped to the tile grid) on each axis, with
    p = (u - 0.5, v - 0.5), r = ceil(3 sqrt(lambda)) and lambda = mid + sqrt(max(0.1, ((a - c) / 2)² + b²))
    for Σ2D = [[a, b], [b, c]]; no 3-sigma cut, but a pixel whose exponent -d²/2 is positive is skipped;
- alpha = min(0.99, opacity · exp(-d²/2)); alpha < 1/255 is skipped;
- front to back by camera-space depth (ties by index); a pixel stops before the Gaussian that would
  bring its transmittance below 1e-4.

Outputs: colour (over a background), alpha = 1 - T, depth accumulated as Σ zᵢ αᵢ Tᵢ ("alpha-weighted")
and its normalisation by alpha ("expected", 0 where alpha is 0), and any per-Gaussian feature channels
composited like colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NEAR, FAR = 0.01, 100.0
EPS2D = 0.3
FOV_CLAMP = 1.3
SIGMA_EXTENT = 3.0
DISCRIMINANT_FLOOR_3DGS = 0.1
TILE_3DGS = 16
FOOTPRINTS = ("ellipse", "3dgs")
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4


@dataclass
class Camera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    world_to_camera: np.ndarray  # [4, 4]


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def project(
    means: np.ndarray, scales: np.ndarray, rotations_wxyz: np.ndarray, cam: Camera
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-space centres [N, 3], pixel centres (u, v) [N, 2] and 2D covariances [N, 2, 2] (with
    the low-pass EPS2D added) of finite Gaussians in front of the camera. No visibility test here."""
    view = np.asarray(cam.world_to_camera, dtype=np.float64)
    rot_w, t_w = view[:3, :3], view[:3, 3]
    p_cam = means @ rot_w.T + t_w
    x, y, z = p_cam[:, 0], p_cam[:, 1], p_cam[:, 2]
    tan_x, tan_y = 0.5 * cam.width / cam.fx, 0.5 * cam.height / cam.fy
    tx = np.clip(x / z, -FOV_CLAMP * tan_x, FOV_CLAMP * tan_x) * z
    ty = np.clip(y / z, -FOV_CLAMP * tan_y, FOV_CLAMP * tan_y) * z
    zeros = np.zeros_like(z)
    jac = np.stack(
        [
            np.stack([cam.fx / z, zeros, -cam.fx * tx / z**2], -1),
            np.stack([zeros, cam.fy / z, -cam.fy * ty / z**2], -1),
        ],
        -2,
    )
    # Σ2D = M Mᵀ with M = J W R S (2 x 3): positive semi-definite by construction.
    m = jac @ rot_w @ quat_wxyz_to_matrix(rotations_wxyz) * scales[:, None, :]
    cov2 = m @ np.swapaxes(m, -1, -2) + EPS2D * np.eye(2)
    uv = np.stack([cam.fx * x / z + cam.cx, cam.fy * y / z + cam.cy], -1)
    return p_cam, uv, cov2


def tiles_3dgs(uv: np.ndarray, cov2: np.ndarray, width: int, height: int) -> tuple[float, tuple[int, int, int, int]]:
    """The 3DGS footprint of one Gaussian: its radius 3 sqrt(lambda) before rounding up, and its tiles
    (x0, y0, x1, y1), [x0, x1) x [y0, y1), possibly empty."""
    a, b, c = cov2[0, 0], cov2[0, 1], cov2[1, 1]
    # 3DGS writes the discriminant as mid² - det: the same number.
    lam = 0.5 * (a + c) + np.sqrt(max(DISCRIMINANT_FLOOR_3DGS, (0.5 * (a - c)) ** 2 + b * b))
    raw = 3.0 * float(np.sqrt(lam))
    r = float(np.ceil(raw))
    px, py = uv[0] - 0.5, uv[1] - 0.5  # 3DGS's pixel coordinates put pixel i at i
    gx, gy = -(-width // TILE_3DGS), -(-height // TILE_3DGS)
    clip = lambda t, n: int(min(max(float(np.floor(t)), 0.0), n))  # noqa: E731
    t = TILE_3DGS
    return raw, (clip((px - r) / t, gx), clip((py - r) / t, gy), clip((px + r + t - 1) / t, gx), clip((py + r + t - 1) / t, gy))


def conic_of(cov2: np.ndarray) -> np.ndarray:
    """Inverse of a 2x2 covariance."""
    det = cov2[0, 0] * cov2[1, 1] - cov2[0, 1] ** 2
    return np.array([[cov2[1, 1], -cov2[0, 1]], [-cov2[0, 1], cov2[0, 0]]]) / det


@dataclass
class Margins:
    """How close a render came to the forward model's discontinuities, over every (pixel, Gaussian)
    pair that was still being composited. A float32 rasterizer can only be held to a tight tolerance
    against this reference where these are not tiny: the fixture generator rejects scenes where they are.

    - `d2`: min |d² - 9| (the 3-sigma cut), over pairs where the cut is a visible step (ellipse only);
    - `alpha`: min |ln(opacity · exp(-d²/2) · 255)| (the 1/255 cut), over pairs inside the footprint;
    - `transmittance`: min |ln(T_next / 1e-4)| (the early stop), over pairs that passed both cuts;
    - `near_far`: min relative distance of a drawn or skipped Gaussian's depth to near and far;
    - `depth_order`: min relative depth gap between two Gaussians that reach a common pixel (an exact
      tie is not counted: it is ordered by index on both sides);
    - `tiles` (3dgs only): how close a Gaussian's tile range came to moving, in pixels: min distance of
      p - r and p + r + 15 from a multiple of 16 (for ends inside or next to the image), and of
      3 sqrt(lambda) from an integer where a radius one pixel larger or smaller would move an end;
      over Gaussians visible (alpha >= 1/510 on a live pixel) in the ring of tiles along the range's edge;
    - `power` (3dgs only): min d² / (|A| dx² + 2 |B dx dy| + |C| dy²) over live pairs in the tiles, for the
      conic (A, B, C): how close the expanded quadratic form came to rounding negative (the positive-
      exponent skip).
    """

    d2: float = np.inf
    alpha: float = np.inf
    transmittance: float = np.inf
    near_far: float = np.inf
    depth_order: float = np.inf
    tiles: float = np.inf
    power: float = np.inf


def render(
    means: np.ndarray,
    scales: np.ndarray,
    rotations_wxyz: np.ndarray,
    opacities: np.ndarray,
    colors: np.ndarray,
    cam: Camera,
    features: np.ndarray | None = None,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    near: float = NEAR,
    far: float = FAR,
    margins: Margins | None = None,
    footprint: str = "ellipse",
) -> dict[str, np.ndarray]:
    """Renders the Gaussians with `footprint` ("ellipse" or "3dgs"); fills `margins` (when given) with
    how close the render came to the model's discontinuities."""
    if footprint not in FOOTPRINTS:
        raise ValueError(f"footprint {footprint!r} is not one of {FOOTPRINTS}")
    f64 = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
    means, scales, rots, opac, cols = map(f64, (means, scales, rotations_wxyz, opacities, colors))
    n = len(opac)
    means, scales, rots, cols = (a.reshape(n, k) for a, k in ((means, 3), (scales, 3), (rots, 4), (cols, 3)))
    feats = f64(features).reshape(n, -1) if features is not None else np.zeros((n, 0))
    h, w = cam.height, cam.width
    rgb = np.zeros((h, w, 3))
    feat_img = np.zeros((h, w, feats.shape[1]))
    depth = np.zeros((h, w))
    trans = np.ones((h, w))
    done = np.zeros((h, w), dtype=bool)

    params = np.concatenate([means, scales, rots, opac[:, None], cols, feats], axis=1)
    finite = np.all(np.isfinite(params), axis=1)
    finite &= np.linalg.norm(np.where(np.isfinite(rots), rots, 0), axis=1) > 0
    safe = lambda a, fill: np.where(finite[:, None], np.nan_to_num(a), fill)  # noqa: E731
    with np.errstate(all="ignore"):
        p_cam, uv, cov2 = project(safe(means, 0.0), safe(scales, 0.0), safe(rots, 1.0), cam)
    z = np.where(finite, p_cam[:, 2], np.nan)
    visible = finite & (z >= near) & (z <= far)
    order = [i for i in np.lexsort((np.arange(n), z)) if visible[i]]
    if margins is not None and finite.any():
        zf = z[finite]
        margins.near_far = float(min(np.abs(zf - near).min() / near, np.abs(zf - far).min() / far))

    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    pix_rows, pix_cols = np.mgrid[0:h, 0:w]
    reach = []
    for i in order:
        det = cov2[i, 0, 0] * cov2[i, 1, 1] - cov2[i, 0, 1] ** 2
        if not det > 0:
            continue
        conic = conic_of(cov2[i])
        u, v = uv[i]
        dx, dy = xs - u, ys - v
        d2 = conic[0, 0] * dx * dx + 2 * conic[0, 1] * dx * dy + conic[1, 1] * dy * dy
        raw = opac[i] * np.exp(-0.5 * d2)
        alpha = np.minimum(ALPHA_MAX, raw)
        if footprint == "ellipse":
            inside = d2 <= SIGMA_EXTENT**2
        else:
            raw_radius, (x0, y0, x1, y1) = tiles_3dgs(uv[i], cov2[i], w, h)
            in_tiles = _tile_mask(pix_rows, pix_cols, (x0, y0, x1, y1))
            inside = in_tiles & (d2 >= 0)  # -d²/2 > 0 is skipped
        hit = inside & (alpha >= ALPHA_MIN) & ~done
        next_t = trans * (1 - alpha)
        if margins is not None:
            if footprint == "ellipse":
                _note_margins(margins, d2, raw, next_t, inside, hit, ~done, opac[i])
                reach.append((z[i], inside))
            else:
                _note_margins(margins, d2, raw, next_t, inside, hit, ~done, opac[i], sigma_cut=False)
                terms = np.abs(conic[0, 0]) * dx * dx + 2 * np.abs(conic[0, 1] * dx * dy) + np.abs(conic[1, 1]) * dy * dy
                live = in_tiles & ~done
                if live.any():
                    with np.errstate(invalid="ignore", divide="ignore"):
                        ratio = np.where(terms > 0, d2 / np.where(terms > 0, terms, 1), np.inf)
                    margins.power = min(margins.power, float(ratio[live].min()))
                margins.tiles = min(margins.tiles, _tiles_margin(uv[i], raw_radius, (x0, y0, x1, y1), raw, ~done, pix_rows, pix_cols, w, h))
                reach.append((z[i], inside & (alpha >= ALPHA_MIN)))
        stop = hit & (next_t < T_MIN)
        done |= stop
        hit &= ~stop
        weight = np.where(hit, alpha * trans, 0.0)
        rgb += weight[..., None] * cols[i]
        feat_img += weight[..., None] * feats[i]
        depth += weight * z[i]
        trans = np.where(hit, next_t, trans)
    if margins is not None:
        margins.depth_order = _depth_order_margin(reach)
    alpha_img = 1 - trans
    expected = np.where(alpha_img > 0, depth / np.where(alpha_img > 0, alpha_img, 1), 0.0)
    return {
        "rgb": rgb + trans[..., None] * np.asarray(background, dtype=np.float64),
        "alpha": alpha_img,
        "depth": depth,
        "expected_depth": expected,
        "features": feat_img,
    }


def _tile_mask(rows: np.ndarray, cols: np.ndarray, rect: tuple[int, int, int, int]) -> np.ndarray:
    x0, y0, x1, y1 = rect
    t = TILE_3DGS
    return (cols >= x0 * t) & (cols < x1 * t) & (rows >= y0 * t) & (rows < y1 * t)


def _tiles_margin(uv, raw_radius, rect, raw, live, rows, cols, w, h) -> float:
    """The `tiles` margin of one Gaussian (inf when its tile range's edge is not a visible step)."""
    x0, y0, x1, y1 = rect
    gx, gy = -(-w // TILE_3DGS), -(-h // TILE_3DGS)
    grown = _tile_mask(rows, cols, (max(x0 - 1, 0), max(y0 - 1, 0), min(x1 + 1, gx), min(y1 + 1, gy)))
    shrunk = _tile_mask(rows, cols, (x0 + 1, y0 + 1, x1 - 1, y1 - 1))
    ring = grown & ~shrunk
    if not (ring & live & (raw >= ALPHA_MIN * 0.5)).any():
        return np.inf
    r = float(np.ceil(raw_radius))
    t = TILE_3DGS
    best = np.inf
    for c, n in ((uv[0] - 0.5, gx), (uv[1] - 0.5, gy)):
        for end in (c - r, c + r + t - 1):
            if -t <= end <= t * (n + 1):
                gap = abs(end - t * round(end / t))
                best = min(best, gap)
                if gap <= 1.0:  # a radius one off would move this end: its rounding counts too
                    best = min(best, abs(raw_radius - round(raw_radius)))
    return best


def _note_margins(margins, d2, raw, next_t, inside, hit, live, opacity, sigma_cut=True) -> None:
    with np.errstate(divide="ignore"):
        # The 3-sigma cut is a step only where the Gaussian is still visible there.
        if sigma_cut and opacity * np.exp(-0.5 * SIGMA_EXTENT**2) >= ALPHA_MIN * 0.5:
            near_cut = live & (np.abs(d2 - SIGMA_EXTENT**2) < 1.0)
            if near_cut.any():
                margins.d2 = min(margins.d2, float(np.abs(d2 - SIGMA_EXTENT**2)[near_cut].min()))
        cand = live & inside
        if cand.any():
            margins.alpha = min(margins.alpha, float(np.abs(np.log(raw[cand] / ALPHA_MIN)).min()))
        if hit.any():
            margins.transmittance = min(margins.transmittance, float(np.abs(np.log(next_t[hit] / T_MIN)).min()))


def _depth_order_margin(reach: list[tuple[float, np.ndarray]], window: float = 1e-3) -> float:
    """Smallest relative depth gap between overlapping Gaussians; gaps of `window` and more are not
    examined (the result is then `window`). `reach` is in depth order."""
    best = window
    for a in range(len(reach)):
        za, ma = reach[a]
        for b in range(a + 1, len(reach)):
            zb, mb = reach[b]
            gap = abs(zb - za) / max(abs(za), abs(zb))
            if gap >= best:
                break
            if gap > 0 and (ma & mb).any():
                best = gap
    return best
