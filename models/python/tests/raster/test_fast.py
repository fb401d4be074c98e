"""The fast tiled rasterizer (data, training, evaluation) against two independent implementations:
its forward pass against the float64 reference on the fixture scenes, and its hand-written backward
pass against PyTorch's autograd through the dense `c4g.raster.dense` (same forward model)."""

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import load_file

from c4g.raster.dense import render
from c4g.raster.fast import render_batch

from tests.common import REPO

def _footprint(path: Path) -> str:
    with safe_open(str(path), "np") as f:
        return (f.metadata() or {}).get("footprint", "ellipse")


# This rasterizer implements the ellipse footprint only (its module doc): the scenes rendered with it.
SCENES = [p for p in sorted((REPO / "models/fixtures/scenes").glob("*.safetensors")) if _footprint(p) == "ellipse"]


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_forward_matches_reference_scene(path: Path):
    s = {k: v.astype(np.float64) if v.dtype == np.float32 else v for k, v in load_file(str(path)).items()}
    t = lambda k: torch.from_numpy(s[k])[None]  # noqa: E731
    if "features" in s:
        # This renderer draws no features; a Gaussian with a non-finite feature is invalid as a whole.
        s["opacities"] = np.where(np.isfinite(s["features"]).all(1), s["opacities"], np.nan)
    width, height = (int(v) for v in s["size"])
    out = render_batch(
        t("positions"), t("scales"), t("rotations"), t("opacities"), t("colors"),
        tuple(s["intrinsics"].tolist()), t("world_to_camera"), width, height, background=t("background"),
    )  # fmt: skip
    # The fixture's expected images were stored as f32: compare at f32 resolution.
    for key in ("rgb", "alpha", "expected_depth"):
        np.testing.assert_allclose(out[key][0].numpy(), s[key], atol=2e-6, rtol=2e-6, err_msg=f"{path.stem}/{key}")


def _scene(seed: int, n: int, batch: int):
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(batch, n, 3, generator=gen, dtype=torch.float64) * 0.3 + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    scales = torch.rand(batch, n, 3, generator=gen, dtype=torch.float64) * 0.06 + 0.02
    rots = torch.randn(batch, n, 4, generator=gen, dtype=torch.float64)
    opac = torch.rand(batch, n, generator=gen, dtype=torch.float64) * 0.7 + 0.1
    cols = torch.rand(batch, n, 3, generator=gen, dtype=torch.float64)
    return [p.requires_grad_() for p in (means, scales, rots, opac, cols)]


def test_gradients_match_autograd_through_the_dense_renderer():
    """Every parameter's gradient of a loss on rgb, alpha and depth, against autograd through
    c4g.raster.dense, image by image (B = 2 with different poses and backgrounds)."""
    params = _scene(1, 48, 2)
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    poses[1, :3, 3] = torch.tensor([0.1, -0.05, 0.2])
    background = torch.tensor([[0.2, 0.3, 0.4], [0.0, 0.0, 0.0]], dtype=torch.float64)
    k = (36.0, 38.0, 16.0, 15.0)
    weights = torch.rand(2, 30, 32, 5, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def loss(out, b=slice(None)):
        return (out["rgb"] * weights[b, ..., :3]).sum() + (out["alpha"] * weights[b, ..., 3]).sum() + (out["depth"] * weights[b, ..., 4]).sum()

    loss(render_batch(*params, k, poses, 32, 30, background=background)).backward()
    fast = [p.grad.clone() for p in params]
    for p in params:
        p.grad = None
    total = 0
    for b in range(2):
        total = total + loss(render(*(p[b] for p in params), k, poses[b], 32, 30, background=background[b]), b)
    total.backward()
    for name, g_fast, p in zip(("means", "scales", "rotations", "opacities", "colors"), fast, params):
        np.testing.assert_allclose(g_fast.numpy(), p.grad.numpy(), rtol=1e-7, atol=1e-9, err_msg=name)
        assert p.grad.abs().sum() > 0, name


def test_invalid_gaussians_get_no_gradient_and_do_not_poison():
    params = _scene(3, 16, 1)
    with torch.no_grad():
        params[0][0, 0] = torch.tensor([0.0, 0.0, -1.0])  # behind the camera
        params[1][0, 1] = float("nan")
    out = render_batch(*params, (30.0, 30.0, 16.0, 16.0), torch.eye(4, dtype=torch.float64)[None], 32, 32)
    out["rgb"].sum().backward()
    assert torch.isfinite(out["rgb"]).all()
    assert params[3].grad[0, 0] == 0 and params[3].grad[0, 1] == 0
    assert torch.isfinite(params[3].grad).all()
