"""The float64 gradient reference (`c4g.raster.grad_reference`) held to the float64 forward reference:
its render equals `reference.render` on the fixture scenes in both footprints, and its autograd gradients
equal central finite differences of `reference.render` (an independent, sequential implementation) on
small scenes. The Rust backward pass is then held to these gradients (renderer/tests/gradient_reference.rs)."""

from pathlib import Path

import numpy as np
import pytest
from safetensors import safe_open

from c4g.raster import reference
from c4g.raster.grad_reference import gradients, scene_gradients, upstream_weights

from tests.common import REPO

SCENES = sorted((REPO / "models/fixtures/scenes").glob("*.safetensors"))


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_the_render_is_the_reference_render(path: Path):
    out, meta = scene_gradients(path)
    with safe_open(str(path), framework="np") as f:
        sc = {k: f.get_tensor(k) for k in f.keys()}
    kept = out["kept"]
    # The fixture's expected planes are the reference's render of all Gaussians, stored as float32; the
    # non-finite ones left out here are skipped there.
    np.testing.assert_allclose(out["rgb"], sc["rgb"].reshape(-1), atol=2e-6, err_msg=meta["scene"])
    np.testing.assert_allclose(out["alpha"], sc["alpha"].reshape(-1), atol=2e-6, err_msg=meta["scene"])
    np.testing.assert_allclose(out["expected_depth"], sc["expected_depth"].reshape(-1), rtol=2e-6, atol=2e-6, err_msg=meta["scene"])
    assert len(kept) == len(out["positions"])
    assert np.isfinite(out["camera"]).all()


def _small_scene(seed: int, n: int = 6):
    rng = np.random.default_rng(seed)
    z = rng.uniform(2.0, 4.0, n)
    means = np.stack([rng.uniform(-0.35, 0.35, n) * z, rng.uniform(-0.35, 0.35, n) * z, z], -1)
    scales = rng.uniform(0.05, 0.17, (n, 3))
    rots = rng.uniform(-1, 1, (n, 4))
    opac = rng.uniform(0.2, 0.97, n)
    cols = rng.uniform(0, 1, (n, 3))
    angle = 0.1
    view = np.eye(4)
    view[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    view[:3, 3] = [0.05, -0.02, 0.1]
    cam = reference.Camera(36.0, 34.0, 20.5, 15.0, 40, 32, view)
    return means, scales, rots, opac, cols, cam


def _loss(params, cam, weights, footprint, tangent=np.zeros(7)):
    means, scales, rots, opac, cols = params
    # A camera increment exp([ω, ν]^) to first order is enough for a derivative at zero only when the
    # step is tiny; use the exact rotation to keep the difference quotient honest.
    w = tangent[:3]
    theta = np.linalg.norm(w)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    rot = np.eye(3) if theta == 0 else np.eye(3) + np.sin(theta) / theta * k + (1 - np.cos(theta)) / theta**2 * k @ k
    view = cam.world_to_camera.copy()
    view[:3, :3] = rot @ view[:3, :3]
    view[:3, 3] = rot @ view[:3, 3] + tangent[3:6]
    f = np.exp(tangent[6])
    c = reference.Camera(cam.fx * f, cam.fy * f, cam.cx, cam.cy, cam.width, cam.height, view)
    r = reference.render(means, scales, rots, opac, cols, c, background=(0.2, 0.4, 0.6), footprint=footprint)
    return float(
        (weights["rgb"] * r["rgb"].reshape(-1)).sum() + (weights["alpha"] * r["alpha"].reshape(-1)).sum() + (weights["expected_depth"] * r["expected_depth"].reshape(-1)).sum()
    )


@pytest.mark.parametrize("footprint", ["ellipse", "3dgs"])
def test_gradients_are_finite_differences_of_the_forward_reference(footprint):
    means, scales, rots, opac, cols, cam = _small_scene(3)
    weights = {k: v.astype(np.float64) for k, v in upstream_weights(cam.width * cam.height, 5).items()}
    g = gradients(means, scales, rots, opac, cols, cam, weights, background=(0.2, 0.4, 0.6), footprint=footprint)
    h = 1e-6
    # In the optimiser's parametrisation: log scale and opacity logit perturb multiplicatively / through
    # the sigmoid.
    cases = []
    for i in range(len(opac)):
        for k in range(3):
            cases.append(("positions", (i, k), lambda p, d, i=i, k=k: p[0].__setitem__((i, k), p[0][i, k] + d)))
            cases.append(("log_scales", (i, k), lambda p, d, i=i, k=k: p[1].__setitem__((i, k), p[1][i, k] * np.exp(d))))
            cases.append(("colors", (i, k), lambda p, d, i=i, k=k: p[4].__setitem__((i, k), p[4][i, k] + d)))
        for k in range(4):
            cases.append(("rotations", (i, k), lambda p, d, i=i, k=k: p[2].__setitem__((i, k), p[2][i, k] + d)))

        def logit(p, d, i=i):
            x = np.log(p[3][i] / (1 - p[3][i])) + d
            p[3][i] = 1 / (1 + np.exp(-x))

        cases.append(("opacity_logits", (i,), logit))
    for name, index, perturb in cases:
        quotient = []
        for d in (h, -h):
            params = [a.copy() for a in (means, scales, rots, opac, cols)]
            perturb(params, d)
            quotient.append(_loss(params, cam, weights, footprint))
        fd = (quotient[0] - quotient[1]) / (2 * h)
        scale = np.abs(g[name]).max()
        assert abs(g[name][index] - fd) <= 1e-6 * scale + 1e-6 * abs(fd), (name, index, g[name][index], fd)
    params = (means, scales, rots, opac, cols)
    for k in range(7):
        tp, tm = np.zeros(7), np.zeros(7)
        tp[k], tm[k] = h, -h
        fd = (_loss(params, cam, weights, footprint, tp) - _loss(params, cam, weights, footprint, tm)) / (2 * h)
        assert abs(g["camera"][k] - fd) <= 1e-6 * np.abs(g["camera"]).max() + 1e-6 * abs(fd), ("camera", k, g["camera"][k], fd)
