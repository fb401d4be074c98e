"""The feature stream (feature lifting) of the mirror, held to the public C4G definition.

- An independent float64 NumPy implementation, written from the equations in
  `../shared/docs/C4G_MODEL.md` (section "Feature stream") and reading the official-layout state
  dict by name, agrees with the mirror run in float64 within 1e-10: both compute the same sums in
  float64 (outputs of order 1, rounding ~1e-15 per operation), so any larger difference is a
  different computation, not rounding.
- The stream never changes the Gaussians (bit for bit), the feature maps do reach the features, and
  feature width 0 leaves the model exactly as it was.
- The official-layout loader accepts a checkpoint with the stream's keys and says so when the
  configuration has no stream.
"""

import numpy as np
import pytest
import torch
from scipy.special import erf

from c4g.model.checkpoint import CheckpointError, feature_dim_of, load_checkpoint, load_into
from c4g.model.config import C4GConfig
from c4g.model.init import random_init
from c4g.model.network import C4G, is_feature_stream

# A very small official-layout model: 2 decoder layers, 2 heads, feature width 6.
CFG = C4GConfig(
    dino_dim=16, dino_depth=1, dino_heads=2, patch=7, pos_embed_grid=4,
    aggregator_dim=16, aggregator_depth=1, aggregator_heads=2,
    decoder_dim=32, decoder_heads=2, decoder_head_dim=16, decoder_mlp=64, decoder_depth=2,
    queries=12, time_dim=16, image_size=28, feature_dim=6,
)  # fmt: skip
FEATURE_KEYS = {
    "gaussian_tokens_feature": (12, 6),
    "gmae_decoder.layers.0.0.to_anotherv.weight": (32, 6),
    "gmae_decoder.layers.0.0.to_yout.0.weight": (6, 32),
    "gmae_decoder.layers.0.0.to_yout.0.bias": (6,),
    "gmae_decoder.layers.0.2.net.0.weight": (6,),
    "gmae_decoder.layers.0.2.net.1.weight": (12, 6),
    "gmae_decoder.layers.0.2.net.4.weight": (6, 12),
    "gmae_decoder.y_norm.weight": (6,),
    "feature_gmae_to_gaussians.weight": (6, 6),
    "feature_gmae_to_gaussians.bias": (6,),
}


def model(cfg: C4GConfig = CFG, seed: int = 3, dtype=torch.float64) -> C4G:
    m = C4G(cfg)
    random_init(m, seed)
    return m.to(dtype).eval()


def inputs(frames: int = 3, targets: int = 2, seed: int = 0, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    p, c = CFG.tokens_per_frame, CFG.feature_width
    features = torch.randn(frames, p, c, generator=gen, dtype=dtype)
    ctx = torch.rand(targets, frames, generator=gen, dtype=dtype)
    tgt = torch.rand(targets, generator=gen, dtype=dtype)
    maps = torch.randn(frames, p, CFG.feature_dim, generator=gen, dtype=dtype)
    return features, ctx, tgt, maps


# -- the independent reference ----------------------------------------------------------------------
def _ln(x, w, b, eps=1e-5):
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + eps) * w + b


def _lin(x, sd, name, bias=True):
    y = x @ sd[name + ".weight"].T
    return y + sd[name + ".bias"] if bias else y


def _mlp(x, sd, name):
    h = _lin(_ln(x, sd[name + ".net.0.weight"], sd[name + ".net.0.bias"]), sd, name + ".net.1")
    return _lin(0.5 * h * (1 + erf(h / np.sqrt(2))), sd, name + ".net.4")


def _heads(x, h):
    return x.reshape(x.shape[0], h, -1).transpose(1, 0, 2)  # [H, L, d]


def reference(sd: dict, cfg: C4GConfig, features, ctx_times, tgt_times, maps):
    """Raw Gaussians [B, N, 14] and features [B, N, F], one target at a time, every row of every layer."""
    # The frequencies are a float32 buffer of the checkpoint (`time_embedding.freqs`): read, not
    # recomputed, since float32 frequencies move the embedding by ~1e-8 relative.
    half = cfg.time_dim // 2
    freqs = sd["time_embedding.freqs"]
    np.testing.assert_allclose(freqs, np.exp(-np.log(10000.0) * np.arange(half) / half), rtol=1e-6)

    def time_mlp(t):
        e = np.concatenate((np.cos(t[..., None] * freqs), np.sin(t[..., None] * freqs)), -1)
        return np.maximum(_lin(np.maximum(_lin(e, sd, "time_mlp.0"), 0), sd, "time_mlp.2"), 0)

    t, p, c = features.shape
    gaussians, lifted = [], []
    for b in range(len(tgt_times)):
        x = np.concatenate(((features + time_mlp(ctx_times[b])[:, None]).reshape(t * p, c), sd["gaussian_tokens"] + time_mlp(tgt_times[b])))
        y = np.concatenate((maps.reshape(t * p, -1), sd["gaussian_tokens_feature"]))
        for i in range(cfg.decoder_depth):
            a = f"gmae_decoder.layers.{i}.0"
            q, k, v = np.split(_lin(_ln(x, sd[a + ".norm.weight"], sd[a + ".norm.bias"]), sd, a + ".to_qkv", bias=False), 3, -1)
            q, k, v = (_heads(z, cfg.decoder_heads) for z in (q, k, v))
            logits = q @ k.transpose(0, 2, 1) / np.sqrt(cfg.decoder_head_dim)
            w = np.exp(logits - logits.max(-1, keepdims=True))
            w /= w.sum(-1, keepdims=True)
            merge = lambda o: o.transpose(1, 0, 2).reshape(len(x), -1)  # noqa: E731
            another_v = _heads(_lin(y, sd, a + ".to_anotherv", bias=False), cfg.decoder_heads)  # y without a norm
            x_attn = _lin(merge(w @ v), sd, a + ".to_out.0")
            y_attn = _lin(merge(w @ another_v), sd, a + ".to_yout.0")
            x, y = x + x_attn, y + y_attn
            x = x + _mlp(x, sd, f"gmae_decoder.layers.{i}.1")
            y = y + _mlp(y, sd, f"gmae_decoder.layers.{i}.2")
        x = _ln(x, sd["gmae_decoder.norm.weight"], sd["gmae_decoder.norm.bias"])
        y = _ln(y, sd["gmae_decoder.y_norm.weight"], sd["gmae_decoder.y_norm.bias"])
        n = cfg.queries
        gaussians.append(_lin(x[-n:], sd, "gmae_to_gaussians"))
        lifted.append(_lin(y[-n:], sd, "feature_gmae_to_gaussians"))
    return np.stack(gaussians), np.stack(lifted)


def test_the_mirror_equals_an_independent_float64_reference():
    m = model()
    sd = {k: v.numpy() for k, v in m.state_dict().items()}
    features, ctx, tgt, maps = inputs(frames=3, targets=2)
    with torch.no_grad():
        raw, lifted = m.decode_raw_with_features(features, ctx, tgt, maps)
    ref_raw, ref_lifted = reference(sd, CFG, features.numpy(), ctx.numpy(), tgt.numpy(), maps.numpy())
    assert lifted.shape == (2, CFG.queries, CFG.feature_dim)
    assert np.abs(ref_lifted).max() > 0.1  # the comparison is not between two near-zero arrays
    np.testing.assert_allclose(lifted.numpy(), ref_lifted, atol=1e-10, rtol=0)
    np.testing.assert_allclose(raw.numpy(), ref_raw, atol=1e-10, rtol=0)


def test_the_feature_stream_never_changes_the_gaussians():
    m = model()
    features, ctx, tgt, maps = inputs()
    with torch.no_grad():
        alone = m.decode_canonical(features, ctx, tgt)
        both, _ = m.decode_with_features(features, ctx, tgt, maps)
        other, _ = m.decode_with_features(features, ctx, tgt, 10 * maps + 3)
    assert torch.equal(alone, both) and torch.equal(alone, other)


def test_each_context_frame_s_map_reaches_the_features_and_the_target_time_does_too():
    m = model()
    features, ctx, tgt, maps = inputs(frames=3, targets=2)
    with torch.no_grad():
        base = m.decode_features(features, ctx, tgt, maps)
        for frame in range(3):
            changed = maps.clone()
            changed[frame] += 1.0
            assert (m.decode_features(features, ctx, tgt, changed) - base).abs().max() > 1e-3
        # Time reaches y only through x's attention weights, and it does reach it.
        assert (m.decode_features(features, ctx, tgt + 0.5, maps) - base).abs().max() > 1e-3


def test_last_layer_on_query_rows_only_is_exact_for_the_features():
    m = model()
    features, ctx, tgt, maps = inputs()
    with torch.no_grad():
        cheap = m.decode_raw_with_features(features, ctx, tgt, maps, query_rows_only=True)[1]
        full = m.decode_raw_with_features(features, ctx, tgt, maps, query_rows_only=False)[1]
    torch.testing.assert_close(cheap, full, atol=1e-12, rtol=0)


def test_feature_width_zero_is_the_model_without_a_stream():
    plain = C4G(C4GConfig.from_dict({**CFG.to_dict(), "feature_dim": 0}))
    assert not plain.has_feature_stream
    assert not any(is_feature_stream(k) for k in plain.state_dict())
    with pytest.raises(ValueError, match="no feature stream"):
        plain.decode_features(*inputs())
    # A seed draws the same Gaussian decoder with or without the stream (its parameters come last).
    random_init(plain, 3)
    with_stream = model(dtype=torch.float32)
    for k, v in plain.state_dict().items():
        assert torch.equal(v, with_stream.state_dict()[k]), k


def test_the_stream_has_the_public_code_s_parameter_names_and_shapes():
    sd = C4G(CFG).state_dict()
    stream = {k: tuple(v.shape) for k, v in sd.items() if is_feature_stream(k)}
    for key, shape in FEATURE_KEYS.items():
        assert stream[key] == shape, key
    # Per layer: to_anotherv, to_yout.0 (weight, bias), y's MLP (3 x weight, bias); then y_norm, tokens, head.
    assert len(stream) == CFG.decoder_depth * (1 + 2 + 6) + 2 + 1 + 2


def test_wrong_map_width_is_refused():
    m = model()
    features, ctx, tgt, maps = inputs()
    with pytest.raises(ValueError, match="feature maps"):
        m.decode_features(features, ctx, tgt, maps[..., :4])


# -- the official-layout loader -------------------------------------------------------------------------
def official_checkpoint(tmp_path, m: C4G):
    path = tmp_path / "with_features.ckpt"
    torch.save({"state_dict": {f"encoder.{k}": v.float() for k, v in m.state_dict().items()}}, path)
    return path


def test_a_checkpoint_with_the_feature_stream_loads_with_every_weight(tmp_path):
    source = model(seed=11, dtype=torch.float32)
    path = official_checkpoint(tmp_path, source)
    loaded = load_checkpoint(path, CFG)
    for k, v in source.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    features, ctx, tgt, maps = inputs(dtype=torch.float32)
    with torch.no_grad():
        torch.testing.assert_close(loaded.decode_features(features, ctx, tgt, maps), source.decode_features(features, ctx, tgt, maps), atol=0, rtol=0)
    assert feature_dim_of({k[len("encoder.") :]: v for k, v in torch.load(path)["state_dict"].items()}) == CFG.feature_dim


def test_a_checkpoint_with_a_stream_into_a_model_without_one_is_refused_with_its_width(tmp_path):
    path = official_checkpoint(tmp_path, model(dtype=torch.float32))
    with pytest.raises(CheckpointError, match="feature stream of width 6"):
        load_checkpoint(path, C4GConfig.from_dict({**CFG.to_dict(), "feature_dim": 0}))


def test_a_checkpoint_without_the_stream_leaves_its_weights_as_initialised():
    """The official checkpoint has no feature stream: the Gaussian weights load, the stream keeps its
    initialisation (the export tool records that in the provenance)."""
    plain = model(C4GConfig.from_dict({**CFG.to_dict(), "feature_dim": 0}), seed=21, dtype=torch.float32)
    target = model(seed=4, dtype=torch.float32)
    before = {k: v.clone() for k, v in target.state_dict().items() if is_feature_stream(k)}
    load_into(target, plain.state_dict())
    assert torch.equal(target.gaussian_tokens, plain.gaussian_tokens)
    for k, v in before.items():
        assert torch.equal(target.state_dict()[k], v), k
    with pytest.raises(CheckpointError, match="missing"):
        load_into(target, plain.state_dict(), allow_missing_feature_stream=False)
