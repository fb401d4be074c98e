"""Every size of the C4G network in one dataclass, so the official model and our small ones share code.

Field names follow the reference (`cases.json` of the reduced reference uses the same names).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class C4GConfig:
    # DINOv2 patch embedding (a whole ViT with registers).
    dino_dim: int = 1024
    dino_depth: int = 24
    dino_heads: int = 16
    dino_mlp_ratio: float = 4.0
    register_tokens: int = 4
    patch: int = 14
    pos_embed_grid: int = 37
    # VGGT aggregator: alternating frame / global blocks.
    aggregator_dim: int = 1024
    aggregator_depth: int = 24
    aggregator_heads: int = 16
    aggregator_mlp_ratio: float = 4.0
    rope_frequency: float = 100.0
    # Gaussian decoder.
    decoder_dim: int = 2048
    decoder_heads: int = 16
    decoder_head_dim: int = 128
    decoder_mlp: int = 4096
    decoder_depth: int = 2
    queries: int = 2048
    time_dim: int = 256
    # Input.
    image_size: int = 224
    # The decoder's feature stream (feature lifting): width F of the 2D feature maps it lifts and of
    # the per-Gaussian features it returns (0 = none: the decoder is the Gaussian stream alone).
    feature_dim: int = 0

    @property
    def grid(self) -> int:
        return self.image_size // self.patch

    @property
    def tokens_per_frame(self) -> int:
        return self.grid * self.grid

    @property
    def special_tokens(self) -> int:
        """Camera token + register tokens before each frame's patches in the aggregator."""
        return 1 + self.register_tokens

    @property
    def feature_width(self) -> int:
        """Width of the encoder output: the concatenation of a frame and a global block's tokens."""
        return 2 * self.aggregator_dim

    def validate(self) -> None:
        if self.decoder_dim != self.feature_width:
            raise ValueError(
                f"decoder_dim ({self.decoder_dim}) must equal 2 x aggregator_dim ({self.feature_width}):"
                " the decoder reads encoder features without a projection"
            )
        if self.decoder_heads * self.decoder_head_dim != self.decoder_dim:
            raise ValueError("decoder_heads x decoder_head_dim must equal decoder_dim")
        if self.image_size % self.patch:
            raise ValueError(f"image_size {self.image_size} is not a multiple of the patch size {self.patch}")
        for name in ("dino", "aggregator"):
            dim, heads = getattr(self, f"{name}_dim"), getattr(self, f"{name}_heads")
            if dim % heads or (dim // heads) % 4:
                raise ValueError(f"{name}_dim / {name}_heads must be a multiple of 4 (2D RoPE halves)")
        if self.time_dim % 2:
            raise ValueError("time_dim must be even (cos and sin halves)")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "C4GConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown config keys: {unknown}")
        return cls(**d)


OFFICIAL = C4GConfig()

# The reduced size of `../shared/reference/c4g-official-small/` (its cases.json "dims").
OFFICIAL_SMALL = C4GConfig(
    dino_dim=64,
    dino_depth=2,
    dino_heads=4,
    aggregator_dim=64,
    aggregator_depth=2,
    aggregator_heads=4,
    decoder_dim=128,
    decoder_heads=16,
    decoder_head_dim=8,
    decoder_mlp=256,
    decoder_depth=2,
    queries=256,
    time_dim=256,
)

PRESETS = {"official": OFFICIAL, "official-small": OFFICIAL_SMALL}
