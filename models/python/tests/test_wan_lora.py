"""The refiner fixture's LoRA files: the PEFT and original-Wan namings hold the same deltas under the
name map, the name map points at real ONNX initializers, and diffusers' own loading agrees."""

import json

import numpy as np
import onnx
import pytest
import torch
from conftest import REPO
from safetensors.torch import load_file

from c4g.wan import configs, export
from c4g.wan import lora as wan_lora

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
