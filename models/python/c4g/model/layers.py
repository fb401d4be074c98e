"""Transformer parts shared by the DINOv2 patch embedding and the VGGT aggregator.

Parameter names (`qkv`, `proj`, `q_norm`, `k_norm`, `ls1.gamma`, `mlp.fc1`, ...) follow the official
checkpoint so that its state dict loads with strict key matching.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .attention import attention


class RotaryEmbedding2D(nn.Module):
    """2D rotary position embedding: the first half of each head's channels rotates with the patch row,
    the second half with the patch column; within each half, channel pairs (i, i + d/2) rotate together.

    The cos / sin tables depend only on positions, which are fixed for a fixed input size, so they are
    computed once per position grid (and become constants in an exported graph).
    """

    def __init__(self, frequency: float):
        super().__init__()
        self.frequency = frequency

    def tables(self, half_dim: int, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        exponents = torch.arange(0, half_dim, 2, dtype=torch.float32) / half_dim
        inv_freq = 1.0 / (self.frequency**exponents)
        max_pos = int(positions.max()) + 1
        angles = torch.arange(max_pos, dtype=torch.float32)[:, None] * inv_freq[None, :]
        angles = torch.cat((angles, angles), dim=-1)
        return angles.cos(), angles.sin()

    def cos_sin(self, head_dim: int, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """cos, sin of shape [L, head_dim] for integer positions [L, 2] given as (row, column)."""
        half = head_dim // 2
        cos, sin = self.tables(half, positions)
        cos = torch.cat((cos[positions[:, 0]], cos[positions[:, 1]]), dim=-1)
        sin = torch.cat((sin[positions[:, 0]], sin[positions[:, 1]]), dim=-1)
        return cos, sin

    @staticmethod
    def apply(x: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        """Rotate x [..., L, head_dim] by the tables from `cos_sin`."""
        # The tables are made in f32 on the CPU; a model cast to bf16 / f16, or moved to a GPU,
        # rotates in its own dtype, on its own device.
        cos, sin = cos.to(x), sin.to(x)
        half = x.shape[-1] // 2
        rotated = []
        for part in (x[..., :half], x[..., half:]):
            a, b = part[..., : half // 2], part[..., half // 2 :]
            rotated.append(torch.cat((-b, a), dim=-1))
        return x * cos + torch.cat(rotated, dim=-1) * sin


class Attention(nn.Module):
    """Multi-head self-attention with a fused qkv projection, optional QK-norm and optional RoPE."""

    def __init__(self, dim: int, heads: int, qk_norm: bool, norm_eps: float = 1e-5):
        super().__init__()
        self.heads = heads
        self.head_dim = dim // heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=True)
        self.q_norm = nn.LayerNorm(self.head_dim, eps=norm_eps) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(self.head_dim, eps=norm_eps) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim, bias=True)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]
        q, k = self.q_norm(q), self.k_norm(k)
        if rope is not None:
            q = RotaryEmbedding2D.apply(q, *rope)
            k = RotaryEmbedding2D.apply(k, *rope)
        merge = lambda t: t.transpose(1, 2).reshape(b, n, c)  # noqa: E731
        return self.proj(attention(merge(q), merge(k), merge(v), self.heads, self.head_dim))


class LayerScale(nn.Module):
    def __init__(self, dim: int, init: float):
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm ViT block with LayerScale: x + ls1(attn(norm1 x)), then x + ls2(mlp(norm2 x))."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, norm_eps: float, qk_norm: bool, ls_init: float = 0.01):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, heads, qk_norm=qk_norm)
        self.ls1 = LayerScale(dim, ls_init)
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim, ls_init)

    def forward(self, x: torch.Tensor, rope: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), rope))
        return x + self.ls2(self.mlp(self.norm2(x)))
