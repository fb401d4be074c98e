"""PyTorch tensors from decoded sets, and the gsplat rendering helper: gsplat is not installed
here (it builds CUDA kernels), so its call is checked against a stand-in module that records
what it was given, and the missing package is checked to fail cleanly."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import Client

torch = pytest.importorskip("torch")


def test_to_torch_keeps_names_shapes_and_values(client: Client, clip: c4g.Clip):
    s = client.decode(clip.id, 0.3)
    t = s.to_torch(device="cpu")
    assert isinstance(t, c4g.TorchGaussianSet) and len(t) == len(s) and t.time == s.time
    for name in ("means", "quats", "scales", "opacities", "colors"):
        tensor = getattr(t, name)
        assert tensor.dtype == torch.float32 and tensor.device.type == "cpu"
        np.testing.assert_array_equal(tensor.numpy(), getattr(s, name))
    assert s.to_torch(dtype=torch.float64).means.dtype == torch.float64
    stacked = c4g.stack(client.decode(clip.id, [0.1, 0.2, 0.3]))
    assert stacked["means"].shape == (3, 512, 3) and stacked["times"].tolist() == [0.1, 0.2, 0.3]


def test_without_pytorch_to_torch_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)  # as if it were not installed
    s = c4g.GaussianSet(0.0, *(np.zeros((1, w), np.float32) for w in (3, 4, 3)), np.zeros(1, np.float32),
                        np.zeros((1, 3), np.float32))  # fmt: skip
    with pytest.raises(ImportError, match=r"torch extra: pip install 'c4g-client\[torch\]'"):
        s.to_torch()


def test_without_gsplat_the_helper_says_what_to_install(client: Client, clip: c4g.Clip, monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # as if it were not installed
    assert isinstance(c4g.GsplatUnavailable("x"), ImportError)
    with pytest.raises(c4g.GsplatUnavailable, match="pip install gsplat"):
        c4g.render_with_gsplat(client.decode(clip.id, 0.3), width=32, height=32, device="cpu")


def test_the_helper_hands_gsplat_the_set_and_camera_in_its_conventions(
    client: Client, clip: c4g.Clip, monkeypatch
):
    calls = []

    def rasterization(**kwargs):
        calls.append(kwargs)
        h, w = kwargs["height"], kwargs["width"]
        colors = torch.full((1, h, w, 3), 0.5)
        colors[0, 0, 0] = torch.tensor([2.0, -1.0, 0.25])
        return colors, torch.ones((1, h, w, 1)), {}

    monkeypatch.setitem(sys.modules, "gsplat", types.SimpleNamespace(rasterization=rasterization))
    s = client.decode(clip.id, 0.3)
    view = np.eye(4)
    view[2, 3] = 0.5
    camera = c4g.Camera(view, c4g.Intrinsics(fx=1.0, fy=0.5, cx=0.5, cy=0.25))
    rendered = c4g.render_with_gsplat(
        s, camera, width=40, height=20, background=(0.1, 0.2, 0.3), device="cpu", rasterize_mode="antialiased"
    )
    (args,) = calls
    np.testing.assert_array_equal(args["means"].numpy(), s.means)
    np.testing.assert_array_equal(args["quats"].numpy(), s.quats)  # wxyz, as gsplat takes them
    np.testing.assert_array_equal(args["scales"].numpy(), s.scales)  # linear, not log
    np.testing.assert_array_equal(args["opacities"].numpy(), s.opacities)  # not logits
    np.testing.assert_array_equal(args["viewmats"].numpy(), view[None].astype(np.float32))
    np.testing.assert_allclose(args["Ks"].numpy(), [[[40, 0, 20], [0, 10, 5], [0, 0, 1]]])
    np.testing.assert_allclose(args["backgrounds"].numpy(), [[0.1, 0.2, 0.3]])
    assert args["rasterize_mode"] == "antialiased" and (args["width"], args["height"]) == (40, 20)
    assert rendered.colors.shape == (20, 40, 3) and rendered.alpha.shape == (20, 40)
    assert rendered.image.array.shape == (20, 40, 3)
    assert rendered.image.array[0, 0].tolist() == [255, 0, 64] and rendered.image.array[1, 1, 0] == 128
    assert rendered._repr_png_().startswith(b"\x89PNG")


@pytest.mark.skipif(not c4g.gsplat_available(), reason="gsplat is not installed")
def test_gsplat_renders_close_to_the_server(client: Client, clip: c4g.Clip):  # pragma: no cover - needs CUDA
    s = client.decode(clip.id, 0.3)
    ours = c4g.render_with_gsplat(s, width=64, height=64)
    server = client.render(clip.id, 0.3, width=64, height=64)
    difference = np.abs(ours.image.array.astype(int) - server.array.astype(int))
    assert difference.mean() < 8
