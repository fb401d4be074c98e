"""The encoder: VGGT's aggregator with its DINOv2 patch embedding.

frames [T, 3, H, W] in [-1, 1] → features [T, P, 2 x aggregator_dim]: the last layer's frame-block and
global-block tokens, concatenated, patch tokens only. The aggregator applies ImageNet mean/std on top of
the [-1, 1] mapping; the official weights were trained with that double normalisation.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .config import C4GConfig
from .layers import Block, RotaryEmbedding2D

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class PatchConv(nn.Module):
    def __init__(self, patch: int, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=patch, stride=patch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


class DinoPatchEmbed(nn.Module):
    """DINOv2 ViT with register tokens, used as the aggregator's patch embedding."""

    def __init__(self, cfg: C4GConfig):
        super().__init__()
        d = cfg.dino_dim
        self.cfg = cfg
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + cfg.pos_embed_grid**2, d))
        self.register_tokens = nn.Parameter(torch.zeros(1, cfg.register_tokens, d))
        # Unused at inference (masked-image training only) but part of the official layout.
        self.mask_token = nn.Parameter(torch.zeros(1, d))
        self.patch_embed = PatchConv(cfg.patch, d)
        self.blocks = nn.ModuleList(
            Block(d, cfg.dino_heads, cfg.dino_mlp_ratio, norm_eps=1e-6, qk_norm=False) for _ in range(cfg.dino_depth)
        )
        self.norm = nn.LayerNorm(d, eps=1e-6)

    def interpolated_pos_embed(self, grid_h: int, grid_w: int) -> torch.Tensor:
        """Positional embedding for a grid_h x grid_w patch grid: the learned 37 x 37 grid resized
        bicubically with antialiasing (as DINOv2 does when the input size differs from training)."""
        g = self.cfg.pos_embed_grid
        pos = self.pos_embed.float()
        cls_pos, patch_pos = pos[:, :1], pos[:, 1:]
        if (grid_h, grid_w) != (g, g):
            patch_pos = patch_pos.reshape(1, g, g, -1).permute(0, 3, 1, 2)
            patch_pos = F.interpolate(patch_pos, size=(grid_h, grid_w), mode="bicubic", antialias=True)
            patch_pos = patch_pos.permute(0, 2, 3, 1).reshape(1, grid_h * grid_w, -1)
        # Resized in f32 (bicubic has no bf16 kernel everywhere), then back to the model's dtype.
        return torch.cat((cls_pos, patch_pos), dim=1).to(self.pos_embed.dtype)

    def forward(self, images: torch.Tensor, pos_embed: torch.Tensor | None = None) -> torch.Tensor:
        n, _, h, w = images.shape
        if pos_embed is None:
            pos_embed = self.interpolated_pos_embed(h // self.cfg.patch, w // self.cfg.patch)
        x = self.patch_embed(images)
        x = torch.cat((self.cls_token.expand(n, -1, -1), x), dim=1) + pos_embed
        x = torch.cat((x[:, :1], self.register_tokens.expand(n, -1, -1), x[:, 1:]), dim=1)
        for block in self.blocks:
            x = block(x)
        return self.norm(x)[:, 1 + self.cfg.register_tokens :]


class Aggregator(nn.Module):
    """Alternating frame attention (within a frame) and global attention (across all frames)."""

    def __init__(self, cfg: C4GConfig):
        super().__init__()
        d = cfg.aggregator_dim
        self.cfg = cfg
        self.patch_embed = DinoPatchEmbed(cfg)
        # Index 0 of dim 1: the first frame's special tokens; index 1: every other frame's.
        self.camera_token = nn.Parameter(torch.zeros(1, 2, 1, d))
        self.register_token = nn.Parameter(torch.zeros(1, 2, cfg.register_tokens, d))
        self.frame_blocks = nn.ModuleList(
            Block(d, cfg.aggregator_heads, cfg.aggregator_mlp_ratio, norm_eps=1e-5, qk_norm=True)
            for _ in range(cfg.aggregator_depth)
        )
        self.global_blocks = nn.ModuleList(
            Block(d, cfg.aggregator_heads, cfg.aggregator_mlp_ratio, norm_eps=1e-5, qk_norm=True)
            for _ in range(cfg.aggregator_depth)
        )
        self.rope = RotaryEmbedding2D(cfg.rope_frequency)
        self.register_buffer("image_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("image_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def token_positions(self, grid_h: int, grid_w: int) -> torch.Tensor:
        """(row, column) per token: 0 for the special tokens, 1-based patch coordinates after them."""
        rows, cols = torch.meshgrid(torch.arange(grid_h), torch.arange(grid_w), indexing="ij")
        patches = torch.stack((rows.flatten(), cols.flatten()), dim=-1) + 1
        special = torch.zeros(self.cfg.special_tokens, 2, dtype=patches.dtype)
        return torch.cat((special, patches), dim=0)

    def special_tokens(self, frames: int) -> torch.Tensor:
        first = torch.cat((self.camera_token[:, 0], self.register_token[:, 0]), dim=1)
        others = torch.cat((self.camera_token[:, 1], self.register_token[:, 1]), dim=1)
        return torch.cat((first, others.expand(frames - 1, -1, -1)), dim=0)

    def forward(
        self,
        images: torch.Tensor,
        pos_embed: torch.Tensor | None = None,
        rope: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """images [T, 3, H, W] in [-1, 1] → features [T, P, 2 x aggregator_dim].

        `pos_embed` and `rope` may be given precomputed (the export does, for a fixed input size)."""
        t, _, h, w = images.shape
        gh, gw = h // self.cfg.patch, w // self.cfg.patch
        if rope is None:
            rope = self.rope.cos_sin(self.cfg.aggregator_dim // self.cfg.aggregator_heads, self.token_positions(gh, gw))
        x = (images - self.image_mean) / self.image_std
        patches = self.patch_embed(x, pos_embed)
        tokens = torch.cat((self.special_tokens(t), patches), dim=1)
        n, c = tokens.shape[1], tokens.shape[2]
        global_rope = (rope[0].repeat(t, 1), rope[1].repeat(t, 1))
        for frame_block, global_block in zip(self.frame_blocks, self.global_blocks):
            frame_out = frame_block(tokens, rope)
            global_out = global_block(frame_out.reshape(1, t * n, c), global_rope).reshape(t, n, c)
            tokens = global_out
        features = torch.cat((frame_out, global_out), dim=-1)
        return features[:, self.cfg.special_tokens :]
