"""Random initialisation that makes every part of the network matter.

PyTorch's defaults leave LayerScale at 0.01, special tokens and positional embeddings at zero, and
the time MLP's contribution tiny: a test model built that way would hide bugs in those parts. This
draws them large enough to move the output (as the reduced official reference does)."""

from __future__ import annotations

import torch

from .network import C4G, is_feature_stream


@torch.no_grad()
def random_init(model: C4G, seed: int, only_prefix: str | None = None) -> None:
    gen = torch.Generator().manual_seed(seed)
    # The feature stream's parameters are drawn last, so that a seed gives the same Gaussian
    # decoder with or without a feature stream (its parameters sit inside the decoder's layers).
    params = sorted(model.named_parameters(), key=lambda item: is_feature_stream(item[0]))
    for name, p in params:
        if only_prefix and not name.startswith(only_prefix):
            continue
        if name.endswith("gamma"):
            p.copy_(torch.rand(p.shape, generator=gen) * 0.25 + 0.05)
        elif name.endswith(("cls_token", "pos_embed", "register_tokens", "camera_token", "register_token", "mask_token")):
            p.copy_(torch.randn(p.shape, generator=gen) * 0.5)
        elif name in ("gaussian_tokens", "gaussian_tokens_feature"):
            p.copy_(torch.randn(p.shape, generator=gen))
        elif p.ndim >= 2:
            fan_in = p[0].numel()
            p.copy_(torch.randn(p.shape, generator=gen) / fan_in**0.5)
        elif "norm" in name and name.endswith("weight"):
            p.copy_(1.0 + 0.1 * torch.randn(p.shape, generator=gen))
        else:
            p.copy_(0.02 * torch.randn(p.shape, generator=gen))
