"""A float64 reference of the 3D Gaussian splatting forward model, written for clarity, not speed.

The renderer crate's CPU and wgpu rasterizers are held against it. Constants are those of the
3DGS convention (docs: ../shared/docs/C4G_MODEL.md, "Rasterisation constants"):

- camera: pinhole, OpenCV (x right, y down, z forward), world-to-camera [R | t]; pixel (i, j) has
  its centre at (i + 0.5, j + 0.5) in the coordinates of cx, cy (so cx = W / 2 is the image centre);
- Gaussians whose camera-space depth is outside [near, far], or with any non-finite parameter, are
  skipped;
- EWA projection: J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] with x/z and y/z clamped to
  1.3 x the half-FOV tangent (W / (2 fx), H / (2 fy)); Σ2D = J W Σ Wᵀ Jᵀ + 0.3 I;
- a Gaussian reaches the pixels within 3 sigma: Mahalanobis distance (under Σ2D) at most 3;
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


def render(
    means: np.ndarray,
    scales: np.ndarray,
    rotations_wxyz: np.ndarray,
    opacities: np.ndarray,
    colors: np.ndarray,
    cam: Camera,
    features: np.ndarray | None = None,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> dict[str, np.ndarray]:
    f64 = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
    means, scales, rots, opac, cols = map(f64, (means, scales, rotations_wxyz, opacities, colors))
    n = means.shape[0]
    feats = f64(features) if features is not None else np.zeros((n, 0))
    h, w = cam.height, cam.width
    rgb = np.zeros((h, w, 3))
    feat_img = np.zeros((h, w, feats.shape[1]))
    depth = np.zeros((h, w))
    trans = np.ones((h, w))
    done = np.zeros((h, w), dtype=bool)

    view = f64(cam.world_to_camera)
    rot_w, t_w = view[:3, :3], view[:3, 3]
    finite = np.all(np.isfinite(np.concatenate([means, scales, rots, opac[:, None], cols, feats], axis=1)), axis=1)
    finite &= np.linalg.norm(np.where(np.isfinite(rots), rots, 0), axis=1) > 0
    p_cam = np.where(finite[:, None], np.nan_to_num(means) @ rot_w.T + t_w, np.nan)
    z = p_cam[:, 2]
    visible = finite & (z >= NEAR) & (z <= FAR)
    order = [i for i in np.lexsort((np.arange(n), z)) if visible[i]]

    tan_x, tan_y = 0.5 * w / cam.fx, 0.5 * h / cam.fy
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    for i in order:
        x, y, zc = p_cam[i]
        tx = np.clip(x / zc, -FOV_CLAMP * tan_x, FOV_CLAMP * tan_x) * zc
        ty = np.clip(y / zc, -FOV_CLAMP * tan_y, FOV_CLAMP * tan_y) * zc
        jac = np.array([[cam.fx / zc, 0.0, -cam.fx * tx / zc**2], [0.0, cam.fy / zc, -cam.fy * ty / zc**2]])
        r = quat_wxyz_to_matrix(rots[i])
        m = r * scales[i][None, :]
        cov3 = m @ m.T
        t_mat = jac @ rot_w
        cov2 = t_mat @ cov3 @ t_mat.T + EPS2D * np.eye(2)
        det = cov2[0, 0] * cov2[1, 1] - cov2[0, 1] ** 2
        if not det > 0:
            continue
        conic = np.array([[cov2[1, 1], -cov2[0, 1]], [-cov2[0, 1], cov2[0, 0]]]) / det
        u, v = cam.fx * x / zc + cam.cx, cam.fy * y / zc + cam.cy
        dx, dy = xs - u, ys - v
        d2 = conic[0, 0] * dx * dx + 2 * conic[0, 1] * dx * dy + conic[1, 1] * dy * dy
        alpha = np.minimum(ALPHA_MAX, opac[i] * np.exp(-0.5 * d2))
        hit = (d2 <= SIGMA_EXTENT**2) & (alpha >= ALPHA_MIN) & ~done
        next_t = trans * (1 - alpha)
        stop = hit & (next_t < T_MIN)
        done |= stop
        hit &= ~stop
        weight = np.where(hit, alpha * trans, 0.0)
        rgb += weight[..., None] * cols[i]
        feat_img += weight[..., None] * feats[i]
        depth += weight * zc
        trans = np.where(hit, next_t, trans)
    alpha_img = 1 - trans
    expected = np.where(alpha_img > 0, depth / np.where(alpha_img > 0, alpha_img, 1), 0.0)
    return {
        "rgb": rgb + trans[..., None] * np.asarray(background, dtype=np.float64),
        "alpha": alpha_img,
        "depth": depth,
        "expected_depth": expected,
        "features": feat_img,
    }
