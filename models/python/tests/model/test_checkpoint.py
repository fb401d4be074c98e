"""Strict loading of checkpoints in the official layout, with readable errors."""

import re

import torch

from c4g.model.checkpoint import PREFIX, ignored_parts, read_state_dict
from c4g.model.config import OFFICIAL, OFFICIAL_SMALL
from c4g.model.network import C4G
from c4g.package import export


def official_keys(path) -> set[str]:
    return set(torch.load(path, map_location="cpu", weights_only=True)["state_dict"])


def test_mirror_has_exactly_the_official_keys(official_small_dir):
    ours = {PREFIX + k for k in C4G(OFFICIAL_SMALL).state_dict()}
    assert ours == official_keys(official_small_dir / "c4g_official_small.ckpt")


def test_official_size_has_the_same_key_layout():
    """The full-size model names its parameters exactly as the reduced one (only shapes differ).
    Built on the meta device: no 0.9B-parameter allocation."""
    with torch.device("meta"):
        full = C4G(OFFICIAL).state_dict()
    small = C4G(OFFICIAL_SMALL).state_dict()
    def layout(keys):  # block indices differ with depth; the names around them must not
        return {re.sub(r"\.\d+\.", ".#.", k) for k in keys}

    assert layout(full) == layout(small)
    assert "backbone.aggregator.frame_blocks.23.attn.q_norm.weight" in full
    assert full["gaussian_tokens"].shape == (2048, 2048)
    assert full["gmae_decoder.layers.0.0.to_qkv.weight"].shape == (6144, 2048)
    assert full["backbone.aggregator.patch_embed.pos_embed"].shape == (1, 1370, 1024)
    assert sum(v.numel() for k, v in full.items() if k.startswith("backbone.")) > 0.85e9


def tampered(src, tmp_path, edit) -> str:
    ckpt = torch.load(src, map_location="cpu", weights_only=True)
    edit(ckpt["state_dict"])
    path = tmp_path / "tampered.ckpt"
    torch.save(ckpt, path)
    return str(path)


def run_export(ckpt, tmp_path, capsys) -> tuple[int, str]:
    rc = export.main(["--checkpoint", ckpt, "--config", "official-small", "--out", str(tmp_path / "out")])
    return rc, capsys.readouterr().err


def test_missing_key_is_named(official_small_dir, tmp_path, capsys):
    key = "encoder.gmae_decoder.layers.1.0.to_qkv.weight"
    ckpt = tampered(official_small_dir / "c4g_official_small.ckpt", tmp_path, lambda sd: sd.pop(key))
    rc, err = run_export(ckpt, tmp_path, capsys)
    assert rc == 2
    assert "1 missing key(s)" in err and key in err
    assert not (tmp_path / "out").exists()


def test_unexpected_key_is_named(official_small_dir, tmp_path, capsys):
    key = "encoder.backbone.camera_head.trunk.0.weight"
    ckpt = tampered(official_small_dir / "c4g_official_small.ckpt", tmp_path, lambda sd: sd.__setitem__(key, torch.zeros(3)))
    rc, err = run_export(ckpt, tmp_path, capsys)
    assert rc == 2 and "1 unexpected key(s)" in err and key in err


def test_shape_mismatch_is_named(official_small_dir, tmp_path, capsys):
    key = "encoder.gaussian_tokens"
    ckpt = tampered(official_small_dir / "c4g_official_small.ckpt", tmp_path, lambda sd: sd.__setitem__(key, torch.zeros(7, 128)))
    rc, err = run_export(ckpt, tmp_path, capsys)
    assert rc == 2 and "shape mismatch" in err and "gaussian_tokens: checkpoint (7, 128) vs model (256, 128)" in err


def test_dpt_head_keys_are_accepted_and_dropped_with_a_word(official_small_dir, tmp_path, capsys):
    ckpt = tampered(
        official_small_dir / "c4g_official_small.ckpt", tmp_path, lambda sd: sd.__setitem__("encoder.dpt_head.proj.weight", torch.zeros(4))
    )
    rc, err = run_export(ckpt, tmp_path, capsys)
    assert rc == 0
    assert "note: dropped 1 key of encoder.dpt_head.* (4 parameters): the DPT head" in err and "depth map" in err


def test_the_reader_says_what_it_drops_and_why(tmp_path):
    """The official checkpoint's DPT head (62 keys, 32.7M parameters) is dropped: the reader names
    the part, counts its keys and parameters, and says why; the model's keys pass through."""
    state = {
        "encoder.gaussian_tokens": torch.zeros(2, 3),
        "encoder.dpt_head.scratch.refinenet1.weight": torch.zeros(3, 4),
        "encoder.dpt_head.head.0.bias": torch.zeros(5),
    }
    path = tmp_path / "official.ckpt"
    torch.save({"state_dict": state}, path)
    said = []
    loaded = read_state_dict(path, report=said.append)
    assert list(loaded) == ["gaussian_tokens"]
    (line,) = said
    assert line.startswith("dropped 2 keys of encoder.dpt_head.* (17 parameters): the DPT head")
    assert "only to visualise a depth map" in line and "inference needs none of it" in line
    assert list(read_state_dict(path)) == ["gaussian_tokens"]  # dropped the same, unasked
    # The official size's count reads in millions; nothing to drop, nothing said.
    with torch.device("meta"):
        official = {f"dpt_head.w{k}": torch.empty(545_000) for k in range(60)}
    assert ignored_parts(official)[0].startswith("dropped 60 keys of encoder.dpt_head.* (32.7M parameters)")
    assert ignored_parts({"gaussian_tokens": torch.zeros(1)}) == []
