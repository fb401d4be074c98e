"""Reference outputs from diffusers for the refiner fixture: schedules, full WanVACEPipeline runs, and
single-model cases, for the Rust pipeline to reproduce.

Every run is on the CPU in float32 with the stock diffusers modules (float64 RoPE tables included),
prompt embeddings passed in (the text side has its own case: captions through the pipeline's
`encode_prompt`), and the initial noise passed as `latents=`, so no random
number generator has to be matched. What each file holds is in `CASES` / `README` below and in the
fixture's reference/README.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from .configs import RefinerConfig

SAMPLER_CASES = [(4, 5.0), (30, 3.0)]
# The WAN_VACE.md test vector (original Wan code: base sigmas linspace(0.999, 0, steps + 1)[:-1]).
WAN_ORIGINAL_4_5 = {"sigmas": [0.9998, 0.937265, 0.833055, 0.624687], "timesteps": [999, 937, 833, 624]}

CONTEXT_FRAMES = 3  # frames 0..2 are context (mask 0); 3.. are regenerated (mask 1) ...
KEEP_BOX = (0, 12, 0, 20)  # ... except rows 0..11, cols 0..19 of the regenerated frames (mask 0 there too)
CONTROL_SCALE = [1.0, 0.5]  # transformer-only case: a different scale per VACE layer


def unipc(shift: float, steps_cfg: dict | None = None):
    from diffusers import UniPCMultistepScheduler

    cfg = dict(steps_cfg or {})
    cfg.update(prediction_type="flow_prediction", use_flow_sigmas=True, flow_shift=shift, num_train_timesteps=1000)
    return UniPCMultistepScheduler(**cfg)


def euler(shift: float):
    from diffusers import FlowMatchEulerDiscreteScheduler

    return FlowMatchEulerDiscreteScheduler(num_train_timesteps=1000, shift=shift)


def sampler_reference() -> dict:
    """sigmas (steps + 1, the last 0) and timesteps (steps) of both schedulers for each (steps, shift)."""
    cases = []
    for steps, shift in SAMPLER_CASES:
        entry: dict = {"steps": steps, "shift": shift}
        for name, sched in (("flow_match_euler", euler(shift)), ("unipc", unipc(shift))):
            sched.set_timesteps(steps)
            entry[name] = {
                "sigmas": [float(s) for s in sched.sigmas],
                "timesteps": [float(t) for t in sched.timesteps],
                "timesteps_dtype": str(sched.timesteps.dtype).removeprefix("torch."),
                "config": {k: v for k, v in sched.config.items() if not k.startswith("_")},
            }
        cases.append(entry)
    return {
        "diffusers_version": _diffusers_version(),
        "cases": cases,
        "wan_original_test_vector": {"steps": 4, "shift": 5.0, **WAN_ORIGINAL_4_5},
    }


def _diffusers_version() -> str:
    import diffusers

    return diffusers.__version__


# ----------------------------------------------------------------------------- inputs


def fixture_inputs(cfg: RefinerConfig, seed: int) -> dict[str, np.ndarray]:
    """Deterministic pipeline inputs: video frames (uint8 / 255, as PIL images reach the pipeline), the
    mask, prompt embeddings zero-padded after their 'real' tokens (as umT5's are), and the initial noise."""
    f, h, w = cfg.frames, cfg.height, cfg.width
    rng = np.random.default_rng(seed)
    t = np.arange(f)[:, None, None]
    y = np.arange(h)[None, :, None]
    x = np.arange(w)[None, None, :]
    channels = [
        0.5 + 0.4 * np.sin(2 * np.pi * (x / w + 0.05 * t)) * np.cos(2 * np.pi * y / h),
        0.5 + 0.4 * np.cos(2 * np.pi * (y / h - 0.07 * t) + x / w),
        (x + y + 2 * t) / (w + h + 2 * f),
    ]
    video = np.stack(channels, axis=-1) + 0.05 * rng.standard_normal((f, h, w, 3))
    video = np.round(np.clip(video, 0, 1) * 255).astype(np.uint8)
    mask = np.ones((f, h, w), dtype=np.uint8)
    mask[:CONTEXT_FRAMES] = 0
    r0, r1, c0, c1 = KEEP_BOX
    mask[CONTEXT_FRAMES:, r0:r1, c0:c1] = 0
    gen = torch.Generator().manual_seed(seed)
    d, length = cfg.transformer["text_dim"], cfg.text_tokens
    prompt = torch.randn(1, length, d, generator=gen)
    prompt[:, (2 * length) // 3 :] = 0
    negative = torch.randn(1, length, d, generator=gen)
    negative[:, length // 3 :] = 0
    noise = torch.randn(cfg.latent_shape, generator=gen)
    return {
        "video": video.astype(np.float32) / 255.0,
        "mask": mask.astype(np.float32),
        "prompt_embeds": prompt.numpy(),
        "negative_prompt_embeds": negative.numpy(),
        "noise": noise.numpy(),
    }


def _pil_frames(video: np.ndarray, mask: np.ndarray):
    from PIL import Image

    frames = [Image.fromarray(np.round(v * 255).astype(np.uint8)) for v in video]
    masks = [Image.fromarray((m * 255).astype(np.uint8)) for m in mask]
    return frames, masks


# ----------------------------------------------------------------------------- pipeline runs


class _Recorder:
    """Forward hooks on the transformer: every call's inputs and output, in call order."""

    def __init__(self, transformer):
        self.calls: list[dict] = []
        self._handles = [
            transformer.register_forward_pre_hook(self._pre, with_kwargs=True),
            transformer.register_forward_hook(self._post, with_kwargs=True),
        ]

    def _pre(self, module, args, kwargs):
        self.calls.append({k: kwargs[k].detach().clone() for k in ("hidden_states", "timestep", "encoder_hidden_states", "control_hidden_states", "control_hidden_states_scale")})

    def _post(self, module, args, kwargs, output):
        self.calls[-1]["output"] = output[0].detach().clone()

    def close(self):
        for h in self._handles:
            h.remove()


def run_pipeline(transformer, vae, scheduler, cfg: RefinerConfig, inputs: dict[str, np.ndarray], guidance_scale: float = 5.0) -> dict[str, np.ndarray]:
    """One WanVACEPipeline run per output type ("latent", then "np") with the same inputs, plus what the
    transformer saw on each call and the VAE's raw (un-normalised) encodings of the control video."""
    from diffusers import WanVACEPipeline

    pipe = WanVACEPipeline(tokenizer=None, text_encoder=None, vae=vae, scheduler=scheduler, transformer=transformer)
    pipe.set_progress_bar_config(disable=True)
    frames, masks = _pil_frames(inputs["video"], inputs["mask"])
    kwargs = dict(
        video=frames,
        mask=masks,
        prompt_embeds=torch.from_numpy(inputs["prompt_embeds"]),
        negative_prompt_embeds=torch.from_numpy(inputs["negative_prompt_embeds"]),
        height=cfg.height,
        width=cfg.width,
        num_frames=cfg.frames,
        num_inference_steps=cfg.steps,
        guidance_scale=guidance_scale,
        conditioning_scale=1.0,
    )
    recorder = _Recorder(transformer)
    try:
        latents = pipe(**kwargs, latents=torch.from_numpy(inputs["noise"]), output_type="latent").frames
        n_calls = len(recorder.calls)
        decoded = {}
        original_decode = vae.decode  # the pipeline calls decode(), not forward(): wrap it to see its input

        def decode(z, return_dict=True):
            decoded["latents"] = z.detach().clone()
            out = original_decode(z, return_dict=return_dict)
            return out

        vae.decode = decode
        try:
            frames_out = pipe(**kwargs, latents=torch.from_numpy(inputs["noise"]), output_type="np").frames
        finally:
            del vae.decode
    finally:
        recorder.close()
    calls = recorder.calls[:n_calls]
    second = recorder.calls[n_calls:]
    assert len(second) == n_calls and all(torch.equal(a["output"], b["output"]) for a, b in zip(calls, second)), "pipeline runs differ"
    cond, uncond = calls[0::2], calls[1::2]
    control = cond[0]["control_hidden_states"]

    # The control tensor's VAE half, un-normalised: what the Rust side's encoder graph must produce.
    video = pipe.video_processor.preprocess_video(frames, cfg.height, cfg.width).float()
    mask = torch.clamp((pipe.video_processor.preprocess_video(masks, cfg.height, cfg.width) + 1) / 2, 0, 1)
    m = torch.where(mask > 0.5, 1.0, 0.0)
    with torch.no_grad():
        inactive = vae.encode(video * (1 - m)).latent_dist.mode()
        reactive = vae.encode(video * m).latent_dist.mode()
    sched = pipe.scheduler
    return {
        **inputs,
        "inactive_latents_raw": inactive.numpy(),
        "reactive_latents_raw": reactive.numpy(),
        "control": control.numpy(),
        "sigmas": sched.sigmas.float().numpy(),
        "timesteps": torch.stack([c["timestep"].float().reshape(()) for c in cond]).numpy(),
        "velocity_first": cond[0]["output"].numpy(),
        "step_latents": torch.stack([c["hidden_states"] for c in cond]).numpy(),
        "step_velocity_cond": torch.stack([c["output"] for c in cond]).numpy(),
        "step_velocity_uncond": torch.stack([c["output"] for c in uncond]).numpy(),
        "latents_final": latents.float().numpy(),
        "decoder_input": decoded["latents"].numpy(),
        "frames_out": np.asarray(frames_out[0], dtype=np.float32),
        "guidance_scale": np.float32(guidance_scale),
        "conditioning_scale": np.ones(len(cfg.transformer["vace_layers"]), dtype=np.float32),
        "shift": np.float32(cfg.shift),
        "steps": np.int64(cfg.steps),
    }


def transformer_case(transformer, cfg: RefinerConfig, seed: int) -> dict[str, np.ndarray]:
    """Random inputs → velocity, from the stock PyTorch transformer (the ONNX graph's check)."""
    tcfg = transformer.config
    gen = torch.Generator().manual_seed(seed)
    f, h, w = cfg.latent_frames, cfg.latent_height, cfg.latent_width
    case = {
        "latents": torch.randn(1, 16, f, h, w, generator=gen),
        "timestep": torch.tensor([937.0]),
        "text_embeddings": torch.randn(1, cfg.text_tokens, tcfg.text_dim, generator=gen),
        "control": torch.randn(1, tcfg.vace_in_channels, f, h, w, generator=gen),
        "control_scale": torch.tensor(CONTROL_SCALE[: len(tcfg.vace_layers)] + [1.0] * max(0, len(tcfg.vace_layers) - len(CONTROL_SCALE))),
    }
    with torch.no_grad():
        velocity = transformer(
            hidden_states=case["latents"],
            timestep=case["timestep"],
            encoder_hidden_states=case["text_embeddings"],
            control_hidden_states=case["control"],
            control_hidden_states_scale=case["control_scale"],
            return_dict=False,
        )[0]
    return {**{k: v.numpy() for k, v in case.items()}, "velocity": velocity.numpy()}


def vae_case(vae, cfg: RefinerConfig, seed: int) -> dict[str, np.ndarray]:
    """video in [-1, 1] → posterior mode; latents → decoded video (stock PyTorch VAE)."""
    gen = torch.Generator().manual_seed(seed)
    video = torch.rand(1, 3, cfg.frames, cfg.height, cfg.width, generator=gen) * 2 - 1
    latents = torch.randn(cfg.latent_shape, generator=gen)
    with torch.no_grad():
        mode = vae.encode(video).latent_dist.mode()
        decoded = vae.decode(latents).sample
    return {"video": video.numpy(), "latents_mode": mode.numpy(), "latents": latents.numpy(), "video_decoded": decoded.numpy()}


# Captions for the text-side reference: plain ones, and each kind of clean-up diffusers' prompt_clean does
# (HTML entities, nested and in a line with a literal "<"; whitespace runs; curly quotes, ligatures, full
# width forms, decomposed accents, terminal escapes and control characters, which ftfy.fix_text repairs),
# the empty negative prompt, one longer than the token budget, and a script the tiny vocabulary lacks.
CAPTIONS = [
    "A red cube slides across a wooden table while the camera slowly orbits the scene.",
    "  two spheres\troll  over a\nchecked floor;\r\nthe camera   stays still.  ",
    "Tom &amp; Jerry &lt;run&gt; &quot;fast&quot; &#39;here&#39; &amp;amp;lt;ok&amp;amp;gt; &eacute;t&eacute;",
    "a <b>bold</b> &amp;amp;amp; line\nthen &amp;amp;amp; another",
    "\u201cQuoted\u201d \u2018single\u2019 it\u2019s \ufb01ne \ufb02owers \uff26\uff35\uff2c\uff2c\u3000wide cafe\u0301",
    "\x1b[31mred\x1b[0m light\x07 \ufeffand a\x00 bell\u2028next line",
    "",
    "A dog runs across a green lawn toward a fence, chasing a ball, while a cyclist rides past a row of trees.",
    "\u4e00\u53ea\u732b\u5728\u684c\u5b50\u4e0a\u8df3 (a cat jumps on a table)",
]


# Pieces of random strings for the clean-up alone (`clean_cases`): entities with and without ';',
# nested, numeric and invalid; markup; each kind of whitespace and line break; C1 controls; curly
# quotes; ligatures; full width; decomposed accents; terminal codes; control characters.
# Left out, as the Rust side does not repair them: mojibake and all-caps entity names (ftfy's). The
# digraph U+01C4 is left out too: it spells "DŽ", and "Ž" beside a C1 control looks like mojibake to
# ftfy, which then re-decodes it.
CLEAN_PIECES = [
    "&amp;", "&amp;amp;", "&lt;", "&gt;", "<", ">", "&copy", "&copyright", "&#39", "&#x27;", "&#0;", "&#128;",
    "&#x1F600;", "&#xD800;", "&#1114112;", "&eacute;", "&nbsp;", "&notit;", "&not", "&;", "&#;", "&#x;",
    " ", "  ", "\t", "\n", "\r\n", "\r", "\u2028", "\x85", "\x93", "\x81", "\u201c", "\u2019", "\u02bc",
    "\ufb01", "\ufb05", "\u01c9", "\uff21", "\uff64", "\u3000", "e\u0301", "\x1b[31m", "\x1b[0;1m", "\x1b",
    "\x00", "\x07", "\x1c", "\ufeff", "\u200b", "\u206a", "word", "Cat", "\u03b4", "\u732b", ";", "#", "&",
]


def clean_cases(count: int = 300, seed: int = 0) -> list[list[str]]:
    """[text, prompt_clean(text)] for random strings of 1-8 `CLEAN_PIECES`."""
    from diffusers.pipelines.wan.pipeline_wan_vace import prompt_clean

    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(count):
        text = "".join(CLEAN_PIECES[i] for i in rng.integers(0, len(CLEAN_PIECES), rng.integers(1, 9)))
        cases.append([text, prompt_clean(text)])
    return cases


def text_case(tokenizer, text_encoder, tokens: int) -> tuple[dict, dict[str, np.ndarray]]:
    """`CAPTIONS` through WanVACEPipeline.encode_prompt (prompt_clean, tokenizer, encoder, cut and pad):
    the cleaned text, token ids and masks (JSON) and the embeddings (npz)."""
    from diffusers import WanVACEPipeline
    from diffusers.pipelines.wan.pipeline_wan_vace import prompt_clean

    pipe = WanVACEPipeline(tokenizer=tokenizer, text_encoder=text_encoder, vae=None, scheduler=unipc(3.0), transformer=None)
    cases, embeddings = [], []
    for caption in CAPTIONS:
        clean = prompt_clean(caption)
        ids = tokenizer([clean], padding="max_length", max_length=tokens, truncation=True, add_special_tokens=True, return_attention_mask=True)
        with torch.no_grad():
            embeds, _ = pipe.encode_prompt(prompt=caption, do_classifier_free_guidance=False, max_sequence_length=tokens, device="cpu")
        cases.append({"caption": caption, "clean": clean, "input_ids": ids["input_ids"][0], "attention_mask": ids["attention_mask"][0]})
        embeddings.append(embeds[0].numpy())
    with torch.no_grad():
        _, negative = pipe.encode_prompt(prompt=CAPTIONS[0], do_classifier_free_guidance=True, max_sequence_length=tokens, device="cpu")
    return {"tokens": tokens, "cases": cases, "clean_cases": clean_cases()}, {"embeddings": np.stack(embeddings), "negative_default": negative[0].numpy()}


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    clean = {}
    for k, v in arrays.items():
        v = np.asarray(v)
        clean[k] = v.astype(np.float32) if v.dtype.kind == "f" else v
    np.savez_compressed(path, **clean)


def write_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2) + "\n")
