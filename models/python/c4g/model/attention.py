"""Scaled dot-product attention on merged-head tensors, exportable as ONNX Runtime's fused
`com.microsoft.MultiHeadAttention`.

In PyTorch it is plain SDPA. Under `fused_export()`, the ONNX export emits the contrib op, whose CPU
kernel runs flash attention (no [L, L] score matrix in memory) and whose CUDA kernel runs fused
attention. The unfused form materialises heads x L x L floats per target: 2.4 GB per decoder layer at
the official size with 16 context frames, which caps how many targets can be decoded at once.
"""

from __future__ import annotations

import contextlib

import torch
import torch.nn.functional as F

_FUSED = False


@contextlib.contextmanager
def fused_export(enabled: bool = True):
    """Within this block, exported graphs use the fused op (PyTorch results are unchanged)."""
    global _FUSED
    previous, _FUSED = _FUSED, enabled
    try:
        yield
    finally:
        _FUSED = previous


def _split(x: torch.Tensor, heads: int) -> torch.Tensor:
    b, n, c = x.shape
    return x.reshape(b, n, heads, c // heads).transpose(1, 2)


def _merge(x: torch.Tensor) -> torch.Tensor:
    b, h, n, d = x.shape
    return x.transpose(1, 2).reshape(b, n, h * d)


class _FusedAttention(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q, k, v, heads: int, scale: float):  # noqa: ARG004
        return _merge(F.scaled_dot_product_attention(_split(q, heads), _split(k, heads), _split(v, heads), scale=scale))

    @staticmethod
    def symbolic(g, q, k, v, heads: int, scale: float):
        return g.op("com.microsoft::MultiHeadAttention", q, k, v, num_heads_i=heads, scale_f=scale)


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, heads: int, head_dim: int) -> torch.Tensor:
    """q [B, Lq, H*D], k [B, L, H*D], v [B, L, H*Dv] → [B, Lq, H*Dv], scale 1/sqrt(D) (D = head_dim,
    a Python number so that it stays a constant in an exported graph)."""
    scale = float(head_dim) ** -0.5
    if _FUSED and torch.onnx.is_in_onnx_export():
        return _FusedAttention.apply(q, k, v, heads, scale)
    return _merge(F.scaled_dot_product_attention(_split(q, heads), _split(k, heads), _split(v, heads), scale=scale))
