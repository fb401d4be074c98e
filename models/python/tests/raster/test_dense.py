"""The differentiable PyTorch rasterizer (training, data) against the float64 reference on the
fixture scenes: two independent implementations of one forward model. In float64 they agree to
1e-9 wherever no pixel sits on a discontinuity (the fixture scenes are made to avoid them)."""

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import load_file

from c4g.raster.dense import render

from tests.common import REPO

def _footprint(path: Path) -> str:
    with safe_open(str(path), "np") as f:
        return (f.metadata() or {}).get("footprint", "ellipse")


# This rasterizer implements the ellipse footprint only (3 sigma): the scenes rendered with it.
SCENES = [p for p in sorted((REPO / "models/fixtures/scenes").glob("*.safetensors")) if _footprint(p) == "ellipse"]


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_matches_reference_scene(path: Path):
    s = {k: v.astype(np.float64) if v.dtype == np.float32 else v for k, v in load_file(str(path)).items()}
    t = lambda k: torch.from_numpy(s[k])  # noqa: E731
    width, height = (int(v) for v in s["size"])
    out = render(
        t("positions"), t("scales"), t("rotations"), t("opacities"), t("colors"),
        tuple(s["intrinsics"].tolist()), t("world_to_camera"), width, height,
        features=t("features") if "features" in s else None, background=t("background"),
    )  # fmt: skip
    # The fixture's expected images were stored as f32: compare at f32 resolution.
    for key, ref in (("rgb", "rgb"), ("alpha", "alpha"), ("expected_depth", "expected_depth"), ("features", "features_image")):
        if ref in s:
            np.testing.assert_allclose(out[key].numpy(), s[ref], atol=2e-6, rtol=2e-6, err_msg=f"{path.stem}/{key}")


def test_gradients_flow_to_every_parameter():
    gen = torch.Generator().manual_seed(0)
    n = 32
    means = (torch.randn(n, 3, generator=gen) * 0.3 + torch.tensor([0.0, 0.0, 2.0])).requires_grad_()
    scales = (torch.rand(n, 3, generator=gen) * 0.05 + 0.02).requires_grad_()
    rots = torch.randn(n, 4, generator=gen).requires_grad_()
    opac = (torch.rand(n, generator=gen) * 0.8 + 0.1).requires_grad_()
    cols = torch.rand(n, 3, generator=gen).requires_grad_()
    out = render(means, scales, rots, opac, cols, (40.0, 40.0, 16.0, 16.0), torch.eye(4), 32, 32)
    (out["rgb"].sum() + out["depth"].sum()).backward()
    for p in (means, scales, rots, opac, cols):
        assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
