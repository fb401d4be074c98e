"""What feature lifting trains on: the 2D feature maps the feature stream takes at the context
frames, the same kind of map at the target views, and the rendered per-Gaussian features compared
with them (C3G's recipe: render the features like colours at the target camera, L1 against the 2D
features of the target view).

Two kinds (`FEATURE_KINDS` of the export tool, declared in the package):
- `encoder`: the model's own encoder patch features, F = the feature width C. Compared at the patch
  level: the rendered feature image (full resolution, every Gaussian's footprint exact) is averaged
  over each patch and held to the target frame's encoder features for that patch. The encoder says
  nothing finer than a patch, so upsampling its features to pixels would only invent a target.
  Both maps are taken without gradient: they are the data, as any 2D feature map would be, and an
  encoder trained through them could make them trivially easy to lift.
- `object-id`: object identity from the synthetic data (`synthetic.render_object_ids`), F =
  `synthetic.OBJECT_IDS`. Context maps: the fraction of each patch's pixels of each id (its one-hot
  averaged over the patch); targets: each pixel's one-hot id at full resolution, held by a
  class-balanced cross-entropy rather than L1 (`loss` says why).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from c4g.model.network import C4G
from c4g.raster.dense import render

from .dataset import Sample
from .synthetic import OBJECT_IDS

KINDS = ("encoder", "object-id")


def feature_width(kind: str, encoder_width: int) -> int:
    """The feature stream's width F for a kind."""
    if kind == "encoder":
        return encoder_width
    if kind == "object-id":
        return OBJECT_IDS
    raise ValueError(f"unknown feature kind {kind!r} (known: {', '.join(KINDS)})")


def _one_hot_ids(sample: Sample, frames: np.ndarray, device: torch.device) -> torch.Tensor:
    if sample.object_ids is None:
        raise ValueError("object-id lifting needs a split made with object ids (python -m c4g.train.dataset --object-ids)")
    return F.one_hot(torch.from_numpy(sample.object_ids[frames]).long().to(device), OBJECT_IDS).float()  # [V, H, W, K]


def _patch_mean(images: torch.Tensor, patch: int) -> torch.Tensor:
    """[V, H, W, F] → [V, H/patch * W/patch, F]: each patch's mean, patches in row-major order (the
    encoder's token order)."""
    pooled = F.avg_pool2d(images.permute(0, 3, 1, 2), patch)
    return pooled.flatten(2).transpose(1, 2)


@torch.no_grad()
def context_maps(model: C4G, sample: Sample, features: torch.Tensor, kind: str) -> torch.Tensor:
    """The feature stream's input at the context frames, [T, P, F]; `features` are the context
    frames' encoder features [T, P, C]."""
    if kind == "encoder":
        return features.detach()
    return _patch_mean(_one_hot_ids(sample, sample.context, features.device), model.cfg.patch)


@torch.no_grad()
def targets(model: C4G, sample: Sample, views: np.ndarray, kind: str) -> torch.Tensor:
    """What the rendered features at `views` are held to: [V, P, C] encoder features of those frames,
    or [V, H, W, K] one-hot object ids."""
    device = model.gaussian_tokens.device
    if kind == "encoder":
        frames = torch.from_numpy(sample.frames[views]).to(device).permute(0, 3, 1, 2) * 2 - 1
        return model.encode(frames)
    return _one_hot_ids(sample, views, device)


def render_features(
    gaussians: tuple, lifted: torch.Tensor, intrinsics: tuple, world_to_camera: torch.Tensor, size: int
) -> torch.Tensor:
    """Per-Gaussian features [V, N, F] of the sets `gaussians` (render_batch's arguments, [V, N, ·])
    composited like colours at each view's camera: [V, H, W, F].

    The blending weights come from the dense rasterizer without gradient, so the feature loss
    trains what is lifted, not the geometry it is lifted onto (colour and depth train that): the
    rendered features are then a product of fixed weights and the features, which costs one
    matrix product a view instead of a second differentiable render."""
    means, scales, rotations, opacities, colours = gaussians
    images = []
    for v in range(len(lifted)):
        with torch.no_grad():
            w = render(means[v], scales[v], rotations[v], opacities[v], colours[v], intrinsics, world_to_camera[v], size, size, weights=True)["weights"]
        images.append((w.T @ lifted[v]).reshape(size, size, -1))
    return torch.stack(images)


def loss(model: C4G, rendered: torch.Tensor, target: torch.Tensor, kind: str) -> torch.Tensor:
    """The rendered feature images [V, H, W, F] against the targets (`targets`): mean L1 for encoder
    features; for object ids, cross-entropy with the rendered channels as logits, each pixel
    weighted by the inverse of its id's share of the view.

    Why not L1 for ids: L1 against one-hot targets is minimised by each channel's median, which for
    any object smaller than half the image is 0, so the stream learns "stage everywhere" (c4g-tiny
    v2's first object-id run did: IoU 0 on every object, at a loss of 0.05). Cross-entropy wants the
    right channel largest, and the balance keeps a small object's pixels from being outvoted."""
    if kind == "encoder":
        return (_patch_mean(rendered, model.cfg.patch) - target).abs().mean()
    labels = target.argmax(dim=-1)  # [V, H, W]
    share = target.mean(dim=(1, 2), keepdim=True)  # [V, 1, 1, K]: each id's share of its view
    weight = (target / share.clamp_min(1e-6)).sum(dim=-1)  # [V, H, W]
    ce = F.cross_entropy(rendered.permute(0, 3, 1, 2), labels, reduction="none")
    return (ce * weight).sum() / weight.sum()
