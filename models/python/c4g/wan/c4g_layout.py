"""C4G's own refinement layout, the one its published LoRA was trained with, as a PyTorch reference.

Written from the facts in WAN_VACE.md ("C4G's own refinement pipeline": the public C4G code runs
refinement through its own fork of DiffSynth-Studio), on top of diffusers' Wan2.1-VACE modules,
which hold the same weights and compute the same functions as DiffSynth's:

- **Sequence.** [K keyframes ; the rendered frames padded to 4k + 1 by repeating the last one]; the
  mask is 0 on keyframes and 1 on rendered frames.
- **VAE per part.** Each keyframe is encoded alone (a one-frame video: one latent frame); the
  rendered part is one causal chunk ((F - 1) / 4 + 1 latent frames). The control input's inactive
  and reactive halves are split the same way (inactive = video * (1 - m), reactive = video * m),
  and so is the mask (8 x 8 unshuffled, resized in time per part with nearest-exact). The denoised
  latents are [keyframe slots ; rendered part].
- **Temporal positions.** Every latent frame carries an explicit temporal RoPE index: a keyframe
  its source-frame index + 500, a rendered latent frame its latent index 0, 1, 2, ... The same
  table serves the main blocks and the VACE blocks (diffusers computes `rotary_emb` once).
- **Sampler.** DiffSynth's flow-matching Euler on the "Wan" schedule: sigmas linspace(1, 0, steps
  + 1)[:-1], shifted by sigma' = s * sigma / (1 + (s - 1) * sigma), timesteps sigma' * 1000 (not
  rounded), x_next = x + v * (sigma_next - sigma) with a final sigma of 0; guidance
  v = v_neg + g * (v_pos - v_neg). The public code's defaults: 50 steps, shift 5, guidance 5.
- **Output.** The rendered part's latents decoded as one chunk; its first F real frames are the
  refined video. The keyframe slots' latents are discarded without decoding: each keyframe decodes
  on its own (one latent frame, no causal context), so skipping them changes nothing else.

Not reproduced: bf16 (the public code runs in bf16; references here are f32, the precision our
graphs are checked at) and the Qwen-VL captioner (the caption comes from the user).
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from torch import nn

from .configs import RefinerConfig

KEYFRAME_POSITION_OFFSET = 500  # DiffSynth's `ref_pos_offset`
DEFAULTS = {"steps": 50, "shift": 5.0, "guidance_scale": 5.0}


class ExplicitTimeRope(nn.Module):
    """diffusers' `WanRotaryPosEmbed` with the temporal index of each latent frame given (`positions`,
    int64 [F']) instead of 0..F'-1; height and width indices as before. The tables are the wrapped
    module's own (float64 in diffusers, float32 once `prepare_transformer_for_export` cast them), so
    positions 0..F'-1 give exactly what the wrapped module gives."""

    def __init__(self, rope: nn.Module):
        super().__init__()
        self.rope = rope
        self.positions: torch.Tensor | None = None

    def forward(self, hidden_states: torch.Tensor):
        _, _, frames, height, width = hidden_states.shape
        p_t, p_h, p_w = self.rope.patch_size
        ppf, pph, ppw = frames // p_t, height // p_h, width // p_w
        positions = self.positions if self.positions is not None else torch.arange(ppf)
        split = [self.rope.t_dim, self.rope.h_dim, self.rope.w_dim]

        def table(freqs: torch.Tensor) -> torch.Tensor:
            t, h, w = freqs.split(split, dim=1)
            parts = [
                t.index_select(0, positions).view(ppf, 1, 1, -1).expand(ppf, pph, ppw, -1),
                h[:pph].view(1, pph, 1, -1).expand(ppf, pph, ppw, -1),
                w[:ppw].view(1, 1, ppw, -1).expand(ppf, pph, ppw, -1),
            ]
            return torch.cat(parts, dim=-1).reshape(1, ppf * pph * ppw, 1, -1)

        return table(self.rope.freqs_cos), table(self.rope.freqs_sin)


def explicit_positions(transformer: nn.Module) -> ExplicitTimeRope:
    """Wraps `transformer.rope` (once) so that its temporal positions can be set per call."""
    if not isinstance(transformer.rope, ExplicitTimeRope):
        transformer.rope = ExplicitTimeRope(transformer.rope)
    return transformer.rope


@contextlib.contextmanager
def positioned(transformer: nn.Module, positions: torch.Tensor):
    rope = explicit_positions(transformer)
    rope.positions = positions
    try:
        yield
    finally:
        rope.positions = None


def positions(keyframe_indices: list[int], rendered_latent_frames: int) -> torch.Tensor:
    """[source index + 500 for each keyframe] + [0, 1, ..., R - 1]."""
    keys = [KEYFRAME_POSITION_OFFSET + int(s) for s in keyframe_indices]
    return torch.tensor(keys + list(range(rendered_latent_frames)), dtype=torch.int64)


def diffsynth_schedule(steps: int, shift: float) -> tuple[np.ndarray, np.ndarray]:
    """(sigmas [steps + 1] ending in 0, timesteps [steps]) of DiffSynth's FlowMatchScheduler as its Wan
    pipelines set it (sigma_max 1, sigma_min 0, extra_one_step), in f64."""
    base = np.linspace(1.0, 0.0, steps + 1)[:-1]
    shifted = shift * base / (1 + (shift - 1) * base)
    return np.append(shifted, 0.0), shifted * 1000.0


def pad_rendered(rendered: np.ndarray, frames: int) -> np.ndarray:
    """[n, H, W, 3] → [frames, H, W, 3], repeating the last frame (n <= frames)."""
    n = rendered.shape[0]
    if not 1 <= n <= frames:
        raise ValueError(f"{n} rendered frames; this layout takes 1..{frames}")
    return np.concatenate([rendered, np.repeat(rendered[-1:], frames - n, axis=0)])


def _video(frames: np.ndarray) -> torch.Tensor:
    """[F, H, W, 3] in [0, 1] → [1, 3, F, H, W] in [-1, 1]."""
    return torch.from_numpy(np.ascontiguousarray(frames, dtype=np.float32)).permute(3, 0, 1, 2)[None] * 2 - 1


def _mask_latent(mask: torch.Tensor, latent_frames: int) -> torch.Tensor:
    """[F, H, W] → [1, 64, latent_frames, H/8, W/8]: 8 x 8 unshuffle (channel dy * 8 + dx), then
    nearest-exact in time, as diffusers' and DiffSynth's VACE code do."""
    f, h, w = mask.shape
    unshuffled = mask.view(f, h // 8, 8, w // 8, 8).permute(2, 4, 0, 1, 3).reshape(64, f, h // 8, w // 8)
    resized = nn.functional.interpolate(unshuffled[None], size=(latent_frames, h // 8, w // 8), mode="nearest-exact")
    return resized


class Latents:
    """The VAE's latent normalisation (`(mode - mean) * (1 / std)` and back), as refiner.json states it."""

    def __init__(self, vae):
        self.mean = torch.tensor(vae.config.latents_mean).view(1, 16, 1, 1, 1)
        self.inv_std = 1.0 / torch.tensor(vae.config.latents_std).view(1, 16, 1, 1, 1)

    def normalise(self, mode: torch.Tensor) -> torch.Tensor:
        return (mode - self.mean) * self.inv_std

    def denormalise(self, latents: torch.Tensor) -> torch.Tensor:
        return latents / self.inv_std + self.mean


@torch.no_grad()
def encode(vae, video: torch.Tensor) -> torch.Tensor:
    return vae.encode(video).latent_dist.mode()


@torch.no_grad()
def control_input(vae, keyframes: np.ndarray, rendered_padded: np.ndarray) -> torch.Tensor:
    """[1, 96, K + R, h, w]: [inactive 16 ; reactive 16 ; mask 64] per latent frame, keyframes first."""
    stats = Latents(vae)
    k, h, w = keyframes.shape[0], keyframes.shape[1], keyframes.shape[2]
    f = rendered_padded.shape[0]
    r = (f - 1) // 4 + 1
    zero_frame = torch.zeros(1, 3, 1, h, w)
    blank = stats.normalise(encode(vae, zero_frame))  # video * m for a keyframe (m = 0): all zeros
    inactive = [stats.normalise(encode(vae, _video(keyframes[i : i + 1]))) for i in range(k)]
    reactive = [blank] * k
    rendered = _video(rendered_padded)
    inactive.append(stats.normalise(encode(vae, torch.zeros_like(rendered))))
    reactive.append(stats.normalise(encode(vae, rendered)))
    mask = torch.cat([_mask_latent(torch.zeros(k, h, w), k), _mask_latent(torch.ones(f, h, w), r)], dim=2)
    return torch.cat([torch.cat(inactive, dim=2), torch.cat(reactive, dim=2), mask], dim=1)


@torch.no_grad()
def velocity(transformer, latents, timestep: float, text, control, position_ids, conditioning_scale: float = 1.0) -> torch.Tensor:
    n_vace = len(transformer.config.vace_layers)
    device = latents.device
    with positioned(transformer, position_ids.to(device)):
        return transformer(
            hidden_states=latents,
            timestep=torch.tensor([timestep], dtype=torch.float32, device=device),
            encoder_hidden_states=text,
            control_hidden_states=control,
            control_hidden_states_scale=torch.full((n_vace,), conditioning_scale, device=device),
            return_dict=False,
        )[0]


@torch.no_grad()
def run(transformer, vae, cfg: RefinerConfig, inputs: dict[str, np.ndarray], steps: int, shift: float, guidance_scale: float) -> dict[str, np.ndarray]:
    """One refinement in C4G's layout, every stage recorded (see the fixture's reference/README.md)."""
    keyframes, rendered = inputs["keyframes"], inputs["rendered"]
    k, n = keyframes.shape[0], rendered.shape[0]
    if k != cfg.keyframes:
        raise ValueError(f"{k} keyframes; the package takes {cfg.keyframes}")
    padded = pad_rendered(rendered, cfg.frames)
    r = cfg.rendered_latent_frames
    control = control_input(vae, keyframes, padded)
    position_ids = positions(list(inputs["keyframe_indices"]), r)
    prompt = torch.from_numpy(inputs["prompt_embeds"])
    negative = torch.from_numpy(inputs["negative_prompt_embeds"])
    sigmas, timesteps = diffsynth_schedule(steps, shift)
    x = torch.from_numpy(inputs["noise"]).clone()
    step_latents, cond_out, uncond_out = [], [], []
    for i, t in enumerate(timesteps):
        step_latents.append(x.clone())
        t32 = float(np.float32(t))
        v_pos = velocity(transformer, x, t32, prompt, control, position_ids)
        v_neg = velocity(transformer, x, t32, negative, control, position_ids)
        cond_out.append(v_pos)
        uncond_out.append(v_neg)
        v = v_neg + guidance_scale * (v_pos - v_neg)
        x = x + v * float(np.float32(sigmas[i + 1]) - np.float32(sigmas[i]))
    stats = Latents(vae)
    decoder_input = stats.denormalise(x[:, :, k:])
    video = vae.decode(decoder_input).sample  # [1, 3, F, H, W], clamped to [-1, 1] by diffusers
    frames = (video[0].permute(1, 2, 3, 0) * 0.5 + 0.5).clamp(0, 1)[:n]
    return {
        **inputs,
        "rendered_padded": padded.astype(np.float32),
        "control": control.numpy(),
        "positions": position_ids.numpy(),
        "sigmas": sigmas.astype(np.float32),
        "timesteps": timesteps.astype(np.float32),
        "velocity_first": cond_out[0].numpy(),
        "step_latents": torch.stack(step_latents).numpy(),
        "step_velocity_cond": torch.stack(cond_out).numpy(),
        "step_velocity_uncond": torch.stack(uncond_out).numpy(),
        "latents_final": x.numpy(),
        "decoder_input": decoder_input.numpy(),
        "frames_out": frames.numpy(),
        "guidance_scale": np.float32(guidance_scale),
        "shift": np.float32(shift),
        "steps": np.int64(steps),
    }


def fixture_inputs(cfg: RefinerConfig, seed: int, rendered_frames: int) -> dict[str, np.ndarray]:
    """Keyframes at source indices 0, 2, 4, ... (as C4G's training windows take every second frame),
    `rendered_frames` rendered frames (fewer than the package's, so padding is exercised), prompt
    embeddings zero-padded after their real tokens, and the initial noise."""
    h, w = cfg.height, cfg.width
    rng = np.random.default_rng(seed)
    y = np.arange(h)[None, :, None]
    x = np.arange(w)[None, None, :]

    def frames(count: int, phase: float) -> np.ndarray:
        t = np.arange(count)[:, None, None] + phase
        channels = [
            0.5 + 0.4 * np.sin(2 * np.pi * (x / w + 0.06 * t)) * np.cos(2 * np.pi * y / h),
            0.5 + 0.4 * np.cos(2 * np.pi * (y / h - 0.05 * t) + x / w),
            (x + 2 * y + 3 * t) / (w + 2 * h + 3 * count),
        ]
        video = np.stack(channels, axis=-1) + 0.05 * rng.standard_normal((count, h, w, 3))
        return (np.round(np.clip(video, 0, 1) * 255) / 255).astype(np.float32)

    gen = torch.Generator().manual_seed(seed)
    d, length = cfg.transformer["text_dim"], cfg.text_tokens
    prompt = torch.randn(1, length, d, generator=gen)
    prompt[:, (2 * length) // 3 :] = 0
    negative = torch.randn(1, length, d, generator=gen)
    negative[:, length // 3 :] = 0
    noise = torch.randn(cfg.latent_shape, generator=gen)
    return {
        "keyframes": frames(cfg.keyframes, 0.0),
        "keyframe_indices": np.arange(cfg.keyframes, dtype=np.int64) * 2,
        "rendered": frames(rendered_frames, 0.5)[:, ::-1].copy(),  # another view: flipped upside down
        "prompt_embeds": prompt.numpy(),
        "negative_prompt_embeds": negative.numpy(),
        "noise": noise.numpy(),
    }


@torch.no_grad()
def frame_encoder_case(vae, cfg: RefinerConfig, seed: int) -> dict[str, np.ndarray]:
    """One frame [1, 3, 1, H, W] in [-1, 1] → its posterior mode [1, 16, 1, h, w] (the frame encoder graph's check)."""
    gen = torch.Generator().manual_seed(seed)
    frame = torch.rand(1, 3, 1, cfg.height, cfg.width, generator=gen) * 2 - 1
    return {"frame": frame.numpy(), "latents_mode": encode(vae, frame).numpy()}
