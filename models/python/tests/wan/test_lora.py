"""The refiner fixture's LoRA files: the PEFT and original-Wan namings hold the same deltas under the
name map, the name map points at real ONNX initializers, and diffusers' own loading agrees."""

import json

import numpy as np
import onnx
import pytest
import torch
from safetensors.torch import load_file, save_file

from c4g.wan import check_merged, configs, export
from c4g.wan import lora as wan_lora

from tests.common import REPO

FIXTURE = REPO / "models/fixtures/wan-vace-tiny"
LORA = FIXTURE / "lora"


@pytest.fixture(scope="module")
def name_map() -> dict:
    return json.loads((LORA / "name_map.json").read_text())


@pytest.fixture(scope="module")
def real_parameters() -> set[str]:
    return {n for n, _ in configs.build_transformer(configs.TRANSFORMER_1_3B, device="meta").named_parameters()}


@pytest.fixture(scope="module")
def peft_config() -> dict:
    return json.loads((LORA / "peft" / "adapter_config.json").read_text())


def test_peft_and_wan_files_hold_the_same_deltas_under_the_name_map(name_map, peft_config):
    peft = wan_lora.deltas_from_peft(LORA / "peft" / "adapter_model.safetensors", peft_config)
    wan = wan_lora.deltas_from_wan(LORA / "wan" / "lora.safetensors")
    assert sorted(peft) == sorted(wan) == sorted(m["onnx_initializer"] for m in name_map["modules"])
    for name in peft:
        torch.testing.assert_close(peft[name], wan[name], atol=1e-7, rtol=0)
    assert peft_config["r"] != peft_config["lora_alpha"]
    assert name_map["scale"] == peft_config["lora_alpha"] / peft_config["r"] == 1.5


def test_every_key_is_named_by_the_map(name_map):
    wan_keys = set(load_file(str(LORA / "wan" / "lora.safetensors")))
    peft_keys = set(load_file(str(LORA / "peft" / "adapter_model.safetensors")))
    expected_wan, expected_peft = set(), set()
    for m in name_map["modules"]:
        expected_wan |= {f"diffusion_model.{m['wan']}{s}" for s in (".lora_down.weight", ".lora_up.weight", ".alpha")}
        expected_peft |= {f"transformer.{m['diffusers']}{s}" for s in (".lora_A.weight", ".lora_B.weight")}
        assert m["onnx_initializer"] == m["diffusers"] + ".weight"
        assert wan_lora.wan_to_diffusers(m["wan"]) == m["diffusers"]
    assert wan_keys == expected_wan and peft_keys == expected_peft


def test_name_map_covers_every_module_kind(name_map):
    wan = {m["wan"] for m in name_map["modules"]}
    for name in (
        "blocks.0.self_attn.q", "blocks.0.self_attn.k", "blocks.0.self_attn.v", "blocks.0.self_attn.o",
        "blocks.1.cross_attn.q", "blocks.1.cross_attn.o", "blocks.2.ffn.0", "blocks.2.ffn.2",
        "vace_blocks.0.before_proj", "vace_blocks.0.after_proj", "vace_blocks.1.after_proj", "vace_blocks.1.self_attn.q",
    ):  # fmt: skip
        assert name in wan, name
    by_wan = {m["wan"]: m["diffusers"] for m in name_map["modules"]}
    assert by_wan["vace_blocks.0.before_proj"] == "vace_blocks.0.proj_in"
    assert by_wan["vace_blocks.1.after_proj"] == "vace_blocks.1.proj_out"
    assert by_wan["blocks.2.ffn.0"] == "blocks.2.ffn.net.0.proj"
    assert by_wan["blocks.1.cross_attn.o"] == "blocks.1.attn2.to_out.0"


def test_name_map_initializers_exist_in_the_graph_with_their_shapes(name_map):
    proto = onnx.load(str(FIXTURE / "transformer.onnx"))
    shapes = {t.name: list(t.dims) for t in proto.graph.initializer}
    wan = load_file(str(LORA / "wan" / "lora.safetensors"))
    for m in name_map["modules"]:
        assert shapes[m["onnx_initializer"]] == m["shape"], m
        up, down = wan[f"diffusion_model.{m['wan']}.lora_up.weight"], wan[f"diffusion_model.{m['wan']}.lora_down.weight"]
        assert [up.shape[0], down.shape[1]] == m["shape"] and up.shape[1] == down.shape[0] == name_map["rank"]


@pytest.mark.parametrize(
    ("wan", "diffusers"),
    [
        ("blocks.12.self_attn.q", "blocks.12.attn1.to_q"),
        ("blocks.3.cross_attn.o", "blocks.3.attn2.to_out.0"),
        ("blocks.29.ffn.2", "blocks.29.ffn.net.2"),
        ("vace_blocks.14.after_proj", "vace_blocks.14.proj_out"),
        ("vace_blocks.0.before_proj", "vace_blocks.0.proj_in"),
        ("vace_blocks.7.cross_attn.k", "vace_blocks.7.attn2.to_k"),
        ("text_embedding.0", "condition_embedder.text_embedder.linear_1"),
        ("time_projection.1", "condition_embedder.time_proj"),
        ("head.head", "proj_out"),
    ],
)
def test_wan_names_map_onto_diffusers_parameters(real_parameters, wan, diffusers):
    assert wan_lora.wan_to_diffusers(wan) == diffusers
    assert wan_lora.diffusers_to_wan(diffusers) == wan
    assert f"{diffusers}.weight" in real_parameters


def test_diffusers_loads_and_fuses_the_peft_file_as_documented():
    """load_lora_weights + fuse_lora (scale 1) gives W + alpha / r * B @ A on exactly the mapped modules,
    and diffusers' converter reads the Wan file's non-VACE keys the same way (export.check_lora_files)."""
    transformer, vae = configs.build_transformer(configs.TINY.transformer, 0), configs.build_vae(configs.TINY.vae, 0)
    fused = export.load_peft_lora_with_diffusers(transformer, vae, LORA / "peft")
    export.check_lora_files(transformer, fused, LORA)


def test_diffusers_rejects_wan_named_vace_keys():
    from diffusers.loaders.lora_conversion_utils import _convert_non_diffusers_wan_lora_to_diffusers

    with pytest.raises(ValueError, match="vace_blocks"):
        _convert_non_diffusers_wan_lora_to_diffusers(load_file(str(LORA / "wan" / "lora.safetensors")))


def test_peft_header_carries_the_adapter_config(peft_config):
    from safetensors import safe_open

    with safe_open(str(LORA / "peft" / "adapter_model.safetensors"), "pt") as f:
        header = json.loads(f.metadata()["lora_adapter_metadata"])
    assert header["transformer.r"] == peft_config["r"] and header["transformer.lora_alpha"] == peft_config["lora_alpha"]
    assert header["transformer.target_modules"] == peft_config["target_modules"]
    assert np.isclose(peft_config["lora_alpha"] / peft_config["r"], 1.5)


# ----------------------------------------------------------------------------- merged at export (--lora)

SMALL = ["--random-init", "--config", "tiny", "--frames", "5", "--height", "16", "--width", "32", "--text-tokens", "8"]


def _onnx_weights(path) -> dict[str, np.ndarray]:
    return {t.name: onnx.numpy_helper.to_array(t) for t in onnx.load(str(path)).graph.initializer}


def test_export_merges_the_lora_into_f32_weights_before_rounding_them_to_f16(tmp_path, peft_config):
    """`--lora --fp16` rounds each adapted weight once: the initializer is exactly f16(W + delta), with
    W and delta in float64, where merging into an already-f16 package rounds twice."""
    lora_file = LORA / "peft" / "adapter_model.safetensors"
    out = tmp_path / "merged"
    assert export.main([*SMALL, "--fp16", "--lora", str(lora_file), "--lora-scale", "0.5", "--out", str(out)]) == 0
    meta = json.loads((out / "refiner.json").read_text())
    merged = meta["lora_merged"]
    deltas = wan_lora.deltas_from_peft(lora_file, peft_config)
    assert (merged["naming"], merged["scale"], merged["modules"], merged["file"]) == ("peft", 0.5, len(deltas), lora_file.name)
    assert meta["precision"] == "f16" and len(merged["sha256"]) == 64

    base = dict(configs.build_transformer(configs.TINY.transformer, 0).named_parameters())
    got = _onnx_weights(out / "transformer.onnx")
    twice_rounded_differs = 0
    for name, delta in deltas.items():
        w = base[name].detach().double()
        expected = (w + 0.5 * delta).half().numpy()
        assert got[name].dtype == np.float16
        np.testing.assert_array_equal(got[name], expected, err_msg=name)
        twice = (w.half().double() + 0.5 * delta).half().numpy()
        twice_rounded_differs += int((twice != expected).sum())
    # Rounding the base first moves some weights by an f16 step: what merging before conversion avoids.
    assert twice_rounded_differs > 0
    # Weights the LoRA does not touch are the plain f16 export's.
    untouched = next(n for n in base if n.endswith(".weight") and n not in deltas and n in got and got[n].dtype == np.float16)
    np.testing.assert_array_equal(got[untouched], base[untouched].detach().half().numpy())
    # And the package runs: ONNX Runtime against the f32 PyTorch transformer with the LoRA merged in f32
    # (measured 1.4e-3 here, and 2e-3 unmerged: docs/benchmarks.md has the 1.3B size).
    assert check_merged.main(["--package", str(out), "--lora", str(lora_file)]) == 0
    with pytest.raises(SystemExit):  # another LoRA than the package's
        check_merged.main(["--package", str(out), "--lora", str(LORA / "wan" / "lora.safetensors")])


@pytest.mark.slow
def test_export_merges_a_wan_named_lora_and_refuses_one_that_does_not_fit(tmp_path, peft_config):
    out = tmp_path / "wan"
    assert export.main([*SMALL, "--lora", str(LORA / "wan" / "lora.safetensors"), "--out", str(out)]) == 0
    assert json.loads((out / "refiner.json").read_text())["lora_merged"]["naming"] == "wan"
    # A PEFT file without adapter_config.json takes the config diffusers' save_lora_weights puts in its header.
    alone = tmp_path / "alone" / "adapter_model.safetensors"
    alone.parent.mkdir()
    header = {f"transformer.{k}": peft_config[k] for k in ("r", "lora_alpha")}
    save_file(load_file(str(LORA / "peft" / "adapter_model.safetensors")), str(alone), metadata={"lora_adapter_metadata": json.dumps(header)})
    assert export.main([*SMALL, "--lora", str(alone.parent), "--out", str(tmp_path / "alone-out")]) == 0
    wan_weights, peft_weights = _onnx_weights(out / "transformer.onnx"), _onnx_weights(tmp_path / "alone-out" / "transformer.onnx")
    for name in wan_lora.deltas_from_peft(LORA / "peft" / "adapter_model.safetensors", peft_config):
        np.testing.assert_allclose(peft_weights[name], wan_weights[name], atol=1e-6, rtol=0)  # the deltas agree to 1e-7

    bad = tmp_path / "bad.safetensors"
    save_file({"diffusion_model.blocks.0.self_attn.q.lora_down.weight": torch.zeros(2, 7), "diffusion_model.blocks.0.self_attn.q.lora_up.weight": torch.zeros(5, 2)}, str(bad))
    with pytest.raises(ValueError, match=r"blocks\.0\.attn1\.to_q.*gives \[5, 7\]"):
        export.main([*SMALL, "--lora", str(bad), "--out", str(tmp_path / "bad")])
    missing = tmp_path / "missing.safetensors"
    save_file({"diffusion_model.blocks.99.self_attn.q.lora_down.weight": torch.zeros(2, 7), "diffusion_model.blocks.99.self_attn.q.lora_up.weight": torch.zeros(5, 2)}, str(missing))
    with pytest.raises(ValueError, match=r"blocks\.99\.attn1\.to_q.* is not a weight"):
        export.main([*SMALL, "--lora", str(missing), "--out", str(tmp_path / "missing")])
