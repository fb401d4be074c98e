"""Train a small C4G (same architecture and parameter names) on the procedural scenes.

    python -m c4g.train.loop --data data/synthetic --run runs/c4g-tiny
    python -m c4g.train.loop --data data/synthetic --run runs/c4g-tiny   # again: resumes from runs/c4g-tiny/last.pt
    python -m c4g.train.loop ... --device cuda --time-budget 420          # on a GPU, stopping (resumable) after 7 minutes

The defaults are c4g-tiny's recipe: 2400 steps, about an hour on 2 CPU cores.

Where it runs is not part of the recipe: `--device` puts the model and every step's tensors on a
device, and the renders follow the tensors (`render_views`): the Numba tiled rasterizer on the CPU,
the dense PyTorch one elsewhere (the same forward model; `tests/train/test_loop.py` holds them to each
other). A run resumes on another device than it started on; steps agree across devices up to float
rounding, not bit for bit.

Per step, a batch of clip windows (T context frames at stride 2, T drawn from --context-frames); each
window is encoded once and decoded at every target between its context frames and at one of its
context frames; the Gaussians are rendered (`render_views`) at the ground-truth cameras.
Loss: MSE (dynamic pixels up-weighted) + SSIM term + depth L1 (of the inverse depth, or of its log:
--depth-loss) + alpha MSE + Chamfer terms
(each Gaussian to the nearest visible ground-truth surface point, and its colour; every such point
to its nearest Gaussian).

Feature lifting (`--features encoder|object-id`, default none: c4g-tiny's recipe): the model gets a
feature stream (`c4g.model.decoder`) as wide as the lifted feature, which takes the context frames' 2D
feature maps; its per-Gaussian features are rendered like colours at each view's camera and held
to the view's own 2D features by an L1 term weighted `--feature-weight` (`c4g.train.lifting` says what
each kind's maps and targets are). Object ids need a split made with `c4g.train.dataset --object-ids`.

Outputs in --run: `last.pt` (full training state, for resuming), `log.jsonl`, and on completion
`c4g-tiny.ckpt` (weights in the official checkpoint layout, for `python -m c4g.package.export`) and
`recipe.json` (every setting and seed, recorded into the package's model.json).

Choices that make the reference architecture trainable from scratch in an hour on a CPU, without
changing what it computes:
- the scale channels are learned through a gain of SCALE_GAIN (folded into the head's weights when
  the checkpoint is written): the head's 0.001 * softplus would otherwise give the scales a
  thousandfold smaller step than everything else;
- patch positions start as a strong 2D sinusoidal code, and the decoder and head start from data
  (`initialise_from_data`): each Gaussian begins as a pixel-aligned splat of one sub-block of the
  first frame. From PyTorch's default initialisation the model spends the whole budget on the
  plateau where every Gaussian has the scene's mean colour.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from c4g.model.checkpoint import feature_dim_of, load_into, read_state_dict, sha256
from c4g.model.config import C4GConfig
from c4g.model.decoder import SH_C0, activate, to_canonical
from c4g.model.network import C4G, is_feature_stream
from c4g.model.time_policy import POLICIES, normalise_batch
from c4g.raster import dense, fast

from . import lifting
from .dataset import Sample, Split, random_windows, span, window
from .synthetic import C4G_FOCAL

TINY = C4GConfig(
    dino_dim=64,
    dino_depth=2,
    dino_heads=4,
    register_tokens=4,
    patch=8,
    pos_embed_grid=8,
    aggregator_dim=64,
    aggregator_depth=3,
    aggregator_heads=4,
    decoder_dim=128,
    decoder_heads=4,
    decoder_head_dim=32,
    decoder_mlp=512,
    decoder_depth=2,
    queries=512,
    time_dim=64,
    image_size=64,
)
SCALE_GAIN = 100.0
ATTENTION_SHARPNESS = 3.0
POSITION_CODE_AMPLITUDE = 5.0
QUERY_GRID = (2, 4)  # queries per patch, as rows x columns of sub-blocks of the patch
INTRINSICS_NORMALISED = C4G_FOCAL  # the renders' intrinsics: C4G's fixed ones, as the data's


def head_gain(dtype=torch.float32) -> torch.Tensor:
    g = torch.ones(14, dtype=dtype)
    g[4:7] = SCALE_GAIN
    return g


@torch.no_grad()
def initialise(model: C4G, seed: int) -> None:
    """PyTorch's default layer initialisation plus the choices documented in the module docstring."""
    torch.manual_seed(seed)
    for m in model.modules():
        if hasattr(m, "reset_parameters") and m is not model:
            m.reset_parameters()
    for name, p in model.named_parameters():
        if name.endswith("gamma"):
            p.fill_(0.1)
        elif name.endswith(("cls_token", "pos_embed", "register_tokens", "camera_token", "register_token", "mask_token")):
            p.normal_(0.0, 0.02)
    model.gaussian_tokens.normal_(0.0, 1.0)
    if model.has_feature_stream:
        model.gaussian_tokens_feature.normal_(0.0, 1.0)
    # Patch positions start as a 2D sinusoidal code rather than near-zero noise: the decoder has no
    # positional encoding of its own, so queries can only find "their" part of the image through
    # positions carried in the features, and with a 0.02-scale code that signal starts buried.
    pos = model.backbone.aggregator.patch_embed.pos_embed
    g, d = model.cfg.pos_embed_grid, pos.shape[-1]
    freqs = 1.0 / (10.0 ** (torch.arange(d // 4, dtype=torch.float32) / (d // 4)))
    rows, cols = torch.meshgrid(torch.arange(g, dtype=torch.float32), torch.arange(g, dtype=torch.float32), indexing="ij")
    r, c = rows.reshape(-1, 1) * freqs, cols.reshape(-1, 1) * freqs
    pos[0, 1:] = POSITION_CODE_AMPLITUDE * torch.cat((r.sin(), r.cos(), c.sin(), c.cos()), dim=-1)
    head = model.gmae_to_gaussians
    d = head.in_features
    head.weight.normal_(0.0, 0.02 / math.sqrt(d))
    head.bias.zero_()
    head.weight[0:3].normal_(0.0, 0.6 / math.sqrt(d))  # xyz spread ~0.6 around the anchor
    head.bias[2] = 1.5  # centre depth 2.5
    head.weight[4:7].normal_(0.0, 0.1 / math.sqrt(d))
    head.bias[4:7] = 0.8  # scale 0.001 * softplus(80) = 0.08 model units
    head.bias[3] = 1.0  # opacity 0.73
    head.bias[10] = 1.0  # rotation x, y, z, w = (0, 0, 0, 1)
    head.weight[11:14].normal_(0.0, 0.5 / math.sqrt(d))


@torch.no_grad()
def initialise_from_data(model: C4G, split: Split, clips: int = 24) -> None:
    """Data-dependent start for the decoder and the head, so that each Gaussian begins as a
    pixel-aligned splat of one place in the first frame (as per-pixel models start) and training
    refines from there instead of from a blur.

    With default weights every query attends almost uniformly to all ~800 tokens (logit spread
    ~0.3), mostly to the other queries; every Gaussian gets the scene's mean colour whatever the
    input, and training sits on that plateau (observed in several runs of 150-340 steps). Instead:
    1. each patch position's mean encoder feature over some training clips (its position code, the
       content averaged out) becomes the query token of the queries assigned to that patch
       (QUERY_GRID of them), and each decoder layer's key projection starts equal to its query
       projection, sharpened: a query's logits are largest for its own patch's tokens;
    2. the head's position and colour rows are fitted by ridge regression on those clips, from the
       queries' final decoder states to the sub-block of the first frame each query stands for (its
       ray, at the clips' median depth, and its mean colour).
    """
    grid, patch = model.cfg.grid, model.cfg.patch
    per_patch = QUERY_GRID[0] * QUERY_GRID[1]
    n = model.cfg.queries
    if n != grid * grid * per_patch:
        raise ValueError(f"{n} queries do not split into {per_patch} per patch of a {grid}x{grid} grid")
    samples = [window(split, clip, 0, 4) for clip in range(min(clips, len(split)))]
    feats = []
    for s in samples:
        frames = torch.from_numpy(s.frames[s.context]).permute(0, 3, 1, 2) * 2 - 1
        feats.append(model.encode(frames))
    per_position = torch.cat(feats).mean(dim=0)  # [P, D]
    tokens = per_position.repeat_interleave(per_patch, dim=0)
    spread = per_position.std(dim=0, keepdim=True)
    model.gaussian_tokens.copy_(tokens + 0.1 * spread * torch.randn_like(tokens))
    for attn, *_ in model.gmae_decoder.layers:
        inner = attn.heads * attn.head_dim
        w = attn.to_qkv.weight
        w[inner : 2 * inner] = w[:inner]
        w[: 2 * inner] *= ATTENTION_SHARPNESS

    # Where each query's sub-block is: patch (row, col) and its cell inside the patch.
    q = torch.arange(n)
    p, k = q // per_patch, q % per_patch
    sub_h, sub_w = patch / QUERY_GRID[0], patch / QUERY_GRID[1]
    v0 = (p // grid) * patch + (k // QUERY_GRID[1]) * sub_h
    u0 = (p % grid) * patch + (k % QUERY_GRID[1]) * sub_w
    size, f = model.cfg.image_size, INTRINSICS_NORMALISED * model.cfg.image_size
    # One depth for every query: the features of a randomly initialised encoder do not predict depth,
    # and a regression onto per-scene depths would smear the rays. Training learns the depth.
    z = float(np.median(np.concatenate([s.depth[0].ravel() for s in samples])))
    states, targets = [], []
    for s, feat in zip(samples, feats):
        ctx, tgt = normalise_batch(s.times[s.context].tolist(), [float(s.times[0])])
        x = model.time_conditioned_tokens(feat, torch.from_numpy(ctx), torch.from_numpy(tgt))
        states.append(model.gmae_decoder(x, query_rows=n)[0])
        img = torch.from_numpy(s.frames[0])
        rows = []
        for i in range(n):
            y0, x0 = int(v0[i]), int(u0[i])
            y1, x1 = int(v0[i] + sub_h), int(u0[i] + sub_w)
            u, v = (x0 + x1) / 2, (y0 + y1) / 2
            rgb = img[y0:y1, x0:x1].reshape(-1, 3).mean(0)
            rows.append(torch.cat((torch.tensor([(u - size / 2) / f * z, (v - size / 2) / f * z, z - 1.0]), (rgb - 0.5) / SH_C0)))
        targets.append(torch.stack(rows))
    x = torch.cat(states)
    x = torch.cat((x, torch.ones(len(x), 1)), dim=1)
    y = torch.cat(targets)
    ridge = 1e-2 * torch.eye(x.shape[1])
    solution = torch.linalg.solve(x.T @ x + ridge, x.T @ y)  # [D + 1, 6]
    head = model.gmae_to_gaussians
    for rows, cols in ((slice(0, 3), slice(0, 3)), (slice(11, 14), slice(3, 6))):
        head.weight[rows] = solution[:-1, cols].T
        head.bias[rows] = solution[-1, cols]


def attach_gain(model: C4G):
    gain = head_gain()
    return model.gmae_to_gaussians.register_forward_hook(lambda _m, _i, out: out * gain.to(out))


@torch.no_grad()
def load_trainable(model: C4G, state: dict[str, torch.Tensor]) -> None:
    """Load an official-layout checkpoint (as `official_state_dict` writes it) for training: the
    head gain comes back out of the head's weights. A feature stream the checkpoint lacks keeps the
    model's initialisation."""
    if feature_dim_of(state) != model.cfg.feature_dim:
        # A feature stream of another width lifts another kind: this run's starts as initialised.
        state = {k: v for k, v in state.items() if not is_feature_stream(k)}
    load_into(model, state)
    gain = head_gain()
    model.gmae_to_gaussians.weight.div_(gain[:, None])
    model.gmae_to_gaussians.bias.div_(gain)


def official_state_dict(model: C4G) -> dict[str, torch.Tensor]:
    """Weights in the official checkpoint layout (prefix `encoder.`), with the head gain folded in."""
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    gain = head_gain()
    state["gmae_to_gaussians.weight"] = state["gmae_to_gaussians.weight"] * gain[:, None]
    state["gmae_to_gaussians.bias"] = state["gmae_to_gaussians.bias"] * gain
    return {f"encoder.{k}": v for k, v in state.items()}


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of [N, 3, H, W] images in [0, 1] (Gaussian window 11, sigma 1.5, valid region)."""
    x = torch.arange(11, dtype=a.dtype, device=a.device) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = (g / g.sum())[:, None] * (g / g.sum())[None, :]
    w = g.expand(3, 1, 11, 11)
    blur = lambda t: F.conv2d(t, w, groups=3)  # noqa: E731
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return s.mean()


def split_canonical(gaussians: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Canonical Gaussians [..., 14] (docs/package.md) → render_batch's arguments: means, scales,
    rotations w-x-y-z, opacities, colours."""
    g = gaussians
    return g[..., 0:3], g[..., 3:6], g[..., 6:10], g[..., 10], g[..., 11:14]


def render_views(gaussians: tuple, intrinsics: tuple, world_to_camera: torch.Tensor, size: int) -> dict[str, torch.Tensor]:
    """Renders [V, N, ·] sets (render_batch's arguments) at [V, 4, 4] poses with the rasterizer for
    the device they are on: the Numba tiled one on the CPU (fast there), the dense PyTorch one on
    any other device (where the Numba kernels cannot run and dense tensors are cheap)."""
    rasterizer = fast if world_to_camera.device.type == "cpu" else dense
    return rasterizer.render_batch(*gaussians, intrinsics, world_to_camera, size, size)


def predict(
    model: C4G, sample: Sample, views: np.ndarray, policy: str = "stable", features_kind: str | None = None
) -> tuple[dict[str, torch.Tensor], tuple]:
    """Encode the sample's context frames, decode at the times of `views` (window indices) and render
    each at its camera. Returns (the renders, the Gaussians as render_batch arguments). With
    `features_kind`, the feature stream lifts that kind's context maps too, and the renders hold the
    rendered features ("features" [V, H, W, F])."""
    # The source frame step the `frame-step` policy reads: the clips' own (frames are evenly timed).
    frame_step = float(sample.times[1] - sample.times[0]) if len(sample.times) > 1 else None
    device = model.gaussian_tokens.device
    frames = torch.from_numpy(sample.frames[sample.context]).to(device).permute(0, 3, 1, 2) * 2 - 1
    features = model.encode(frames)
    ctx_times, tgt_times = normalise_batch(sample.times[sample.context].tolist(), sample.times[views].tolist(), policy, frame_step)
    ctx_times, tgt_times = torch.from_numpy(ctx_times).to(device), torch.from_numpy(tgt_times).to(device)
    if features_kind is None:
        decoded, lifted = model.decode(features, ctx_times, tgt_times), None
    else:
        maps = lifting.context_maps(model, sample, features, features_kind)
        raw, lifted = model.decode_raw_with_features(features, ctx_times, tgt_times, maps)
        decoded = activate(raw, model.anchor_positions.to(raw.dtype))
    size = model.cfg.image_size
    f = INTRINSICS_NORMALISED * size
    intrinsics = (f, f, size / 2, size / 2)
    poses = torch.from_numpy(sample.world_to_camera[views]).float().to(device)
    gaussians = split_canonical(to_canonical(decoded))
    out = render_views(gaussians, intrinsics, poses, size)
    if lifted is not None:
        out["features"] = lifting.render_features(gaussians, lifted, intrinsics, poses, size)
    return out, gaussians


def surface_points(sample: Sample, views: np.ndarray, count: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """`count` ground-truth surface points per view (unprojected from its depth, model frame) and
    their colours: [V, count, 3] each."""
    v, h, w = sample.depth[views].shape
    f = INTRINSICS_NORMALISED * w
    pick = rng.choice(h * w, count, replace=False)
    ys, xs = np.divmod(pick, w)
    z = sample.depth[views].reshape(v, -1)[:, pick]
    cam = np.stack(((xs + 0.5 - w / 2) / f * z, (ys + 0.5 - h / 2) / f * z, z), -1)  # [V, count, 3]
    c2w = np.linalg.inv(sample.world_to_camera[views])
    world = np.einsum("vij,vkj->vki", c2w[:, :3, :3], cam) + c2w[:, None, :3, 3]
    colours = sample.frames[views].reshape(v, -1, 3)[:, pick]
    return torch.from_numpy(world).float(), torch.from_numpy(colours)


def loss_terms(
    out: dict[str, torch.Tensor], gaussians: tuple, sample: Sample, views: np.ndarray, dynamic_weight: float, rng: np.random.Generator,
    depth_loss: str = "inverse",
) -> dict[str, torch.Tensor]:
    device = out["rgb"].device
    gt = torch.from_numpy(sample.frames[views]).to(device)
    dyn = torch.from_numpy(sample.dynamic[views]).float().to(device)
    w = (1 + dynamic_weight * dyn)[..., None]
    mse = ((out["rgb"] - gt) ** 2 * w).mean() / w.mean()
    s = ssim(out["rgb"].permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2))
    gt_depth = torch.from_numpy(sample.depth[views]).to(device)
    mask = (gt_depth > 0) & (out["alpha"] > 0.3)
    predicted, truth = out["expected_depth"].clamp_min(1e-3), gt_depth.clamp_min(1e-3)
    if depth_loss == "log":
        # The same relative error costs the same at every distance: a slow camera puts the scene
        # tens of baselines away, where inverse depth (and the Chamfer terms, relative to the
        # view's depth) give the depth almost no gradient.
        error = (predicted.log() - truth.log()).abs()
    else:
        error = (1 / predicted - 1 / truth).abs()
    depth = (error * mask).sum() / mask.sum().clamp_min(1)
    alpha = ((out["alpha"] - (gt_depth > 0).float()) ** 2).mean()
    # Chamfer terms against the visible ground-truth surface at each view's moment: every Gaussian is
    # pulled onto the nearest surface point and takes its colour; every surface point wants a
    # Gaussian near it. Rendering alone lets a few large, half-transparent Gaussians blur the scene
    # into its mean colour; this gives each Gaussian its own target.
    points, colours = (t.to(device) for t in surface_points(sample, views, 1024, rng))
    means, rgb = gaussians[0], gaussians[4]
    # Distances relative to each view's median depth: scenes range over an order of magnitude in
    # model units (the unit is the camera baseline), and far walls should not dominate.
    scale = points[..., 2:3].median(dim=1, keepdim=True).values.clamp_min(1e-3)
    d = torch.cdist(means, points) / scale  # [V, N, K]
    to_surface, nearest = d.min(dim=2)
    coverage = d.min(dim=1).values
    colour = ((rgb - torch.gather(colours, 1, nearest[..., None].expand(-1, -1, 3))) ** 2).mean()
    return {"mse": mse, "ssim": s, "depth": depth, "alpha": alpha, "chamfer": to_surface.mean() + coverage.mean(), "colour": colour}


def psnr(mse: float) -> float:
    return 10 * math.log10(1 / max(mse, 1e-12))


@torch.no_grad()
def validate(model: C4G, split: Split, context_frames: int, policy: str = "stable") -> dict[str, float]:
    """PSNR at the targets between context frames, on the first window of every validation clip."""
    model.eval()
    errors = []
    for clip in range(len(split)):
        s = window(split, clip, 0, context_frames)
        out, _ = predict(model, s, s.targets, policy)
        errors.append(float(((out["rgb"].cpu().clamp(0, 1) - torch.from_numpy(s.frames[s.targets])) ** 2).mean()))
    model.train()
    return {"val_psnr": float(np.mean([psnr(e) for e in errors]))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.train.loop", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="folder with train.npz and validation.npz (python -m c4g.train.dataset)")
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=2400)
    ap.add_argument("--batch", type=int, default=4, help="clip windows per step")
    ap.add_argument("--context-frames", default="3,4", help="T is drawn per step from these")
    ap.add_argument("--strides", default="2", help="source frames between context frames, drawn per step from these (pairs with T that fit the clips)")
    ap.add_argument("--time-policy", choices=sorted(POLICIES), default="stable", help="the time normalisation trained with (the package declares it)")
    ap.add_argument("--lr", type=float, default=8e-4)
    ap.add_argument("--warmup", type=int, default=150)
    ap.add_argument("--dynamic-weight", type=float, default=3.0, help="extra MSE weight on pixels of moving objects")
    ap.add_argument("--ssim-weight", type=float, default=0.2)
    ap.add_argument("--depth-weight", type=float, default=0.1)
    ap.add_argument("--depth-loss", choices=["inverse", "log"], default="inverse", help="L1 of the expected depth's inverse (c4g-tiny's recipe) or of its log")
    ap.add_argument("--alpha-weight", type=float, default=0.1)
    ap.add_argument("--surface-weight", type=float, default=0.5, help="weight of the Chamfer position and colour terms")
    ap.add_argument("--features", choices=["none", *lifting.KINDS], default="none", help="feature lifting: what the feature stream learns to lift")
    ap.add_argument("--feature-weight", type=float, default=1.0, help="weight of the rendered features' L1 term")
    ap.add_argument("--feature-stream-only", action="store_true", help="train the feature stream alone, on the loss of its rendered features, every other weight held as --init-from gives it")
    ap.add_argument("--init-from", type=Path, default=None, help="start from this checkpoint (official layout, as this tool writes it: c4g-tiny v2 starts from v1); a feature stream it lacks starts as initialised")
    ap.add_argument("--targets-per-window", type=int, default=None, help="render at most this many of a window's targets (drawn per step); default all of them")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="where the model and the steps run (cpu, cuda, cuda:1, ...); not part of the recipe")
    ap.add_argument("--time-budget", type=float, default=None, help="stop (with a checkpoint) once a step ends this many seconds into this invocation; run again to resume")
    ap.add_argument("--checkpoint-every", type=int, default=100)
    ap.add_argument("--validate-every", type=int, default=300)
    ap.add_argument("--stop-after", type=int, default=None, help="stop (with a checkpoint) after this many steps in this invocation; run again to resume")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print(f"error: --device {args.device}: this PyTorch sees no CUDA device", file=sys.stderr)
        return 2
    args.run.mkdir(parents=True, exist_ok=True)
    # Defaults that c4g-tiny (v1) was trained before they existed are left out of its recipe, so
    # its runs still resume and its recipe stays as it was.
    v1_defaults = {"strides": "2", "time_policy": "stable", "init_from": None, "targets_per_window": None, "feature_stream_only": False, "depth_loss": "inverse"}
    # Feature lifting's settings are recorded only when it is on (so a run without stays c4g-tiny's).
    lifting_settings = ("features", "feature_weight") if args.features == "none" else ()
    recipe = {
        k: (str(v) if isinstance(v, Path) else v)
        for k, v in vars(args).items()
        if k not in ("run", "threads", "device", "time_budget", "checkpoint_every", "validate_every", "stop_after", *lifting_settings) and v1_defaults.get(k, object()) != v
    }
    features_kind = None if args.features == "none" else args.features
    cfg = TINY
    if features_kind is not None:
        cfg = C4GConfig.from_dict({**TINY.to_dict(), "feature_dim": lifting.feature_width(features_kind, TINY.feature_width)})
    recipe.update(
        config=cfg.to_dict(),
        scale_gain=SCALE_GAIN,
        attention_sharpness=ATTENTION_SHARPNESS,
        position_code_amplitude=POSITION_CODE_AMPLITUDE,
        query_grid=list(QUERY_GRID),
        time_policy=args.time_policy,
        optimizer="AdamW(0.9, 0.99), wd 0.01 on matrices, cosine to 10%, grad clip 1",
    )

    train, val = Split.load(args.data / "train.npz"), Split.load(args.data / "validation.npz")
    recipe.update(train_clips=len(train), validation_clips=len(val), train_seeds=[int(train.seeds.min()), int(train.seeds.max())])
    if features_kind == "object-id" and train.object_ids is None:
        print("error: --features object-id needs a split made with object ids (python -m c4g.train.dataset --object-ids)", file=sys.stderr)
        return 2
    model = C4G(cfg)
    initialise(model, args.seed)
    if args.init_from is None:
        initialise_from_data(model, train)
    else:
        load_trainable(model, read_state_dict(args.init_from))
        recipe["init_from_sha256"] = sha256(args.init_from)
    attach_gain(model)
    # Initialised (from data, or a checkpoint) on the CPU; trained where asked.
    model.to(device)
    if args.feature_stream_only:
        if features_kind is None or args.init_from is None:
            print("error: --feature-stream-only trains a feature stream (--features) on a model from --init-from", file=sys.stderr)
            return 2
        for name, p in model.named_parameters():
            p.requires_grad_(is_feature_stream(name))
    trained = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    decay = [p for n, p in trained if p.ndim >= 2 and "token" not in n and "pos_embed" not in n]
    rest = [p for n, p in trained if not (p.ndim >= 2 and "token" not in n and "pos_embed" not in n)]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": 0.01}, {"params": rest, "weight_decay": 0.0}], lr=args.lr, betas=(0.9, 0.99))
    step = 0
    last = args.run / "last.pt"
    if last.exists():
        state = torch.load(last, weights_only=False, map_location=device)
        if state["recipe"] != recipe:
            print("error: last.pt was written with a different recipe; use a new --run folder", file=sys.stderr)
            return 2
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        step = state["step"]
        print(f"resumed at step {step}")
    frames = train.frames.shape[1]
    choices = [int(c) for c in args.context_frames.split(",")]
    strides = [int(s) for s in args.strides.split(",")]
    fitting = {t: [s for s in strides if span(t, s) <= frames] for t in choices}
    if not all(fitting.values()):
        print(f"error: some --context-frames fit no --strides in the training clips ({frames} frames): {fitting}", file=sys.stderr)
        return 2
    log = (args.run / "log.jsonl").open("a")
    model.train()
    t0 = time.time()
    end = args.steps if args.stop_after is None else min(args.steps, step + args.stop_after)
    while step < end:
        # Every step's data is a function of (seed, step): a resumed run sees what it would have seen.
        rng = np.random.default_rng([args.seed, step])
        lr = args.lr * min(1.0, (step + 1) / args.warmup) * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * step / args.steps)))
        for g in opt.param_groups:
            g["lr"] = lr
        t = int(rng.choice(choices))
        # One stride draws nothing more, so c4g-tiny's recipe sees the same data as it did.
        stride = fitting[t][0] if len(strides) == 1 else int(rng.choice(fitting[t]))
        totals: dict[str, float] = {}
        opt.zero_grad()
        for sample in random_windows(train, rng, args.batch, t, stride):
            targets = sample.targets
            if args.targets_per_window is not None and len(targets) > args.targets_per_window:
                targets = np.sort(rng.choice(targets, args.targets_per_window, replace=False))
            views = np.concatenate((targets, rng.choice(sample.context, 1)))
            out, gaussians = predict(model, sample, views, args.time_policy, features_kind)
            terms = loss_terms(out, gaussians, sample, views, args.dynamic_weight, rng, args.depth_loss)
            if features_kind is not None:
                target = lifting.targets(model, sample, views, features_kind)
                terms["feature"] = lifting.loss(model, out["features"], target, features_kind)
            if args.feature_stream_only:
                loss = terms["feature"]
            else:
                loss = (
                    terms["mse"]
                    + args.ssim_weight * (1 - terms["ssim"])
                    + args.depth_weight * terms["depth"]
                    + args.alpha_weight * terms["alpha"]
                    + args.surface_weight * (terms["chamfer"] + terms["colour"])
                    + (args.feature_weight * terms["feature"] if features_kind is not None else 0.0)
                )
            (loss / args.batch).backward()
            for k, v in terms.items():
                totals[k] = totals.get(k, 0.0) + float(v.detach()) / args.batch
        grad_norm = float(torch.nn.utils.clip_grad_norm_([p for _, p in trained], 1.0))
        opt.step()
        step += 1
        record = {"step": step, "lr": lr, "T": t, "stride": stride, "grad_norm": grad_norm, "psnr": psnr(totals["mse"]), **totals, "elapsed_s": time.time() - t0}
        if step % args.validate_every == 0 or step == args.steps:
            record.update(validate(model, val, 4, args.time_policy))
        log.write(json.dumps(record) + "\n")
        log.flush()
        if step % 10 == 0 or "val_psnr" in record:
            print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in record.items()), flush=True)
        out_of_time = args.time_budget is not None and time.time() - t0 >= args.time_budget
        if step % args.checkpoint_every == 0 or step == end or out_of_time:
            tmp = last.with_suffix(".tmp")
            torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step, "recipe": recipe}, tmp)
            tmp.replace(last)
        if out_of_time:
            break
    if step < args.steps:
        print(f"stopped at step {step} of {args.steps}; run the same command again to resume")
        return 0
    torch.save({"state_dict": official_state_dict(model)}, args.run / "c4g-tiny.ckpt")
    (args.run / "recipe.json").write_text(json.dumps(recipe, indent=2) + "\n")
    (args.run / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
    print(f"wrote {args.run / 'c4g-tiny.ckpt'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
