"""Model configurations for the refiner: the tiny random-weight stand-in and the real Wan2.1-VACE-1.3B.

Both are diffusers configs (`WanVACETransformer3DModel`, `AutoencoderKLWan`), so the same classes build
either. The tiny one keeps every structural feature of the real model (patch (1, 2, 2), 16 latent
channels, 96 control channels, QK RMS-norm across heads, cross-attention norm, VACE layers that start at
0 and skip one block, 3-D RoPE, a causal 3-D VAE with 4x temporal and 8x spatial compression) at sizes a
CPU runs in milliseconds. The video size is not square (32 x 48) so that a height / width mix-up shows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

# Wan2.1-VACE-1.3B as diffusers ships it (transformer/config.json of Wan-AI/Wan2.1-VACE-1.3B-diffusers).
TRANSFORMER_1_3B: dict = {
    "patch_size": [1, 2, 2],
    "num_attention_heads": 12,
    "attention_head_dim": 128,
    "in_channels": 16,
    "out_channels": 16,
    "text_dim": 4096,
    "freq_dim": 256,
    "ffn_dim": 8960,
    "num_layers": 30,
    "cross_attn_norm": True,
    "qk_norm": "rms_norm_across_heads",
    "eps": 1e-6,
    "image_dim": None,
    "added_kv_proj_dim": None,
    "rope_max_seq_len": 1024,
    "pos_embed_seq_len": None,
    "vace_layers": list(range(0, 30, 2)),
    "vace_in_channels": 96,
}

# The Wan2.1 VAE (diffusers' AutoencoderKLWan defaults, which are the released model's).
VAE_WAN21: dict = {
    "base_dim": 96,
    "z_dim": 16,
    "dim_mult": [1, 2, 4, 4],
    "num_res_blocks": 2,
    "attn_scales": [],
    "temperal_downsample": [False, True, True],
    "dropout": 0.0,
    # fmt: off
    "latents_mean": [-0.7571, -0.7089, -0.9113, 0.1075, -0.1745, 0.9653, -0.1517, 1.5508,
                     0.4134, -0.0715, 0.5517, -0.3632, -0.1922, -0.9497, 0.2503, -0.2921],
    "latents_std": [2.8184, 1.4541, 2.3275, 2.6558, 1.2196, 1.7708, 2.6052, 2.0743,
                    3.2687, 2.1526, 2.8652, 1.5579, 1.6382, 1.1253, 2.8251, 1.9160],
    # fmt: on
}

# 2 heads x 16 (RoPE split of the head dim: 8 frames / 4 height / 4 width), 4 blocks, VACE at 0 and 2.
TRANSFORMER_TINY: dict = {
    **TRANSFORMER_1_3B,
    "num_attention_heads": 2,
    "attention_head_dim": 16,
    "text_dim": 32,
    "ffn_dim": 64,
    "num_layers": 4,
    "vace_layers": [0, 2],
}

# Channels 4 / 8 / 16 / 16, one residual block per level; latent statistics are the real model's.
VAE_TINY: dict = {**VAE_WAN21, "base_dim": 4, "num_res_blocks": 1}


@dataclass(frozen=True)
class RefinerConfig:
    """What the export needs to know: the two diffusers configs and the fixed video size of the graphs."""

    name: str
    transformer: dict
    vae: dict
    frames: int
    height: int
    width: int
    text_tokens: int
    fps: int = 16
    shift: float = 3.0
    steps: int = 30
    guidance_scale: float = 5.0
    scheduler: dict = field(default_factory=dict)
    # C4G's layout (c4g_layout.py): K keyframe slots before the `frames` rendered frames; 0 = VACE's.
    keyframes: int = 0

    @property
    def rendered_latent_frames(self) -> int:
        """Latent frames of the `frames`-frame video the VAE graphs take (one causal chunk)."""
        return (self.frames - 1) // 4 + 1

    @property
    def latent_frames(self) -> int:
        """Latent frames the transformer takes: keyframe slots, then the video's."""
        return self.keyframes + self.rendered_latent_frames

    @property
    def rendered_latent_shape(self) -> list[int]:
        return [1, 16, self.rendered_latent_frames, self.latent_height, self.latent_width]

    @property
    def latent_height(self) -> int:
        return self.height // 8

    @property
    def latent_width(self) -> int:
        return self.width // 8

    @property
    def latent_shape(self) -> list[int]:
        return [1, 16, self.latent_frames, self.latent_height, self.latent_width]

    @property
    def tokens(self) -> int:
        p = self.transformer["patch_size"]
        return self.latent_frames // p[0] * (self.latent_height // p[1]) * (self.latent_width // p[2])

    def validate(self) -> None:
        if (self.frames - 1) % 4:
            raise ValueError(f"frames must be 4k + 1 (the VAE's causal time chunks), got {self.frames}")
        if self.height % 16 or self.width % 16:
            raise ValueError(f"height and width must be multiples of 16 (VAE 8 x patch 2), got {self.height} x {self.width}")


# UniPC as WanVACEPipeline uses it (the diffusers checkpoints' scheduler_config.json), flow_shift set per run.
UNIPC_FLOW: dict = {
    "num_train_timesteps": 1000,
    "prediction_type": "flow_prediction",
    "use_flow_sigmas": True,
    "solver_order": 2,
    "solver_type": "bh2",
    "predict_x0": True,
    "lower_order_final": True,
    "final_sigmas_type": "zero",
}

TINY = RefinerConfig(
    name="wan-vace-tiny", transformer=TRANSFORMER_TINY, vae=VAE_TINY, frames=9, height=32, width=48, text_tokens=16,
    shift=5.0, steps=4, scheduler={**UNIPC_FLOW, "flow_shift": 5.0},
)
WAN_1_3B = RefinerConfig(
    name="wan2.1-vace-1.3b", transformer=TRANSFORMER_1_3B, vae=VAE_WAN21, frames=81, height=480, width=832, text_tokens=512,
    shift=3.0, steps=30, scheduler={**UNIPC_FLOW, "flow_shift": 3.0},
)
# C4G's layout at the tiny size: 3 keyframes and 5 rendered frames (2 latent frames): 5 latent frames.
TINY_C4G = RefinerConfig(
    name="wan-vace-tiny-c4g", transformer=TRANSFORMER_TINY, vae=VAE_TINY, frames=5, height=32, width=48, text_tokens=16,
    shift=5.0, steps=3, guidance_scale=5.0, keyframes=3,
)
PRESETS = {"tiny": TINY, "1.3b": WAN_1_3B}


def build_transformer(cfg: dict, seed: int | None = None, device: str | torch.device = "cpu"):
    """A `WanVACETransformer3DModel` from `cfg`. With `seed`, deterministic random weights (see `randomise`)."""
    from diffusers import WanVACETransformer3DModel

    if seed is not None:
        torch.manual_seed(seed)
    with torch.device(device):
        model = WanVACETransformer3DModel(**cfg)
    if seed is not None and str(device) != "meta":
        randomise(model, seed)
    return model.eval()


def build_vae(cfg: dict, seed: int | None = None, device: str | torch.device = "cpu"):
    """An `AutoencoderKLWan` from `cfg`. With `seed`, deterministic random weights (see `randomise`)."""
    from diffusers import AutoencoderKLWan

    if seed is not None:
        torch.manual_seed(seed)
    with torch.device(device):
        model = AutoencoderKLWan(**cfg)
    if seed is not None and str(device) != "meta":
        randomise(model, seed + 1)
    return model.eval()


@torch.no_grad()
def randomise(model: torch.nn.Module, seed: int) -> None:
    """PyTorch's default init leaves norm scales at 1 and some biases at 0. Give every parameter that is
    constant a small random perturbation, so that no two parameters hold identical values (a name mix-up
    between them would otherwise go unnoticed) and every weight matters to the output."""
    gen = torch.Generator().manual_seed(seed)
    for _, p in sorted(model.named_parameters()):
        if p.numel() > 1 and bool((p == p.flatten()[0]).all()):
            p.add_(0.1 * torch.randn(p.shape, generator=gen, dtype=p.dtype))


def parameter_count(cfg: dict, vae: bool = False) -> int:
    """Parameters of the model built from `cfg`, counted on the meta device (no memory, any size)."""
    model = build_vae(cfg, device="meta") if vae else build_transformer(cfg, device="meta")
    return sum(p.numel() for p in model.parameters())


def transformer_parameter_count(cfg: dict) -> dict[str, int]:
    """The transformer's parameters worked out by hand from the config: the base DiT and the VACE branch
    (a check on the meta-device count, and the doc's ~1.42B + ~0.73B for the 1.3B model)."""
    d = cfg["num_attention_heads"] * cfg["attention_head_dim"]
    f, t, fd = cfg["ffn_dim"], cfg["text_dim"], cfg["freq_dim"]
    p = math.prod(cfg["patch_size"])
    attn = 4 * (d * d + d) + 2 * d  # q, k, v, o with bias + the two RMS norms across heads
    block = 2 * attn + (d * f + f) + (f * d + d) + 6 * d + (2 * d if cfg["cross_attn_norm"] else 0)
    embed = (
        (cfg["in_channels"] * p * d + d)  # patch_embedding
        + (fd * d + d) + (d * d + d)  # time_embedder
        + (d * 6 * d + 6 * d)  # time_proj
        + (t * d + d) + (d * d + d)  # text_embedder
        + (d * cfg["out_channels"] * p + cfg["out_channels"] * p) + 2 * d  # proj_out, scale_shift_table
    )
    base = embed + cfg["num_layers"] * block
    n_vace = len(cfg["vace_layers"])
    vace = (cfg["vace_in_channels"] * p * d + d) + n_vace * (block + d * d + d) + (d * d + d)  # + proj_out each, proj_in once
    return {"base": base, "vace": vace, "total": base + vace}
