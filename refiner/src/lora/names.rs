//! LoRA key names: which tensor of which module a key holds, and the module's diffusers name.
//!
//! Two conventions exist for the same modules. The original Wan checkpoint (and ComfyUI /
//! DiffSynth LoRAs trained on it) says `blocks.3.self_attn.q`; diffusers, PEFT adapters trained
//! with it, and our ONNX export say `blocks.3.attn1.to_q`. We translate the first into the second
//! and leave names already in the second alone; whether the result exists is decided against the
//! ONNX file, so a key we cannot place is an error there, never silently dropped.

/// What one LoRA tensor is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Part {
    /// `lora_A` / `lora_down`: `[r, in]` (or `[r, in, k…]` for a convolution).
    Down,
    /// `lora_B` / `lora_up`: `[out, r]` (or `[out, r, 1…]`).
    Up,
    /// `alpha`: a scalar; the scale is `alpha / r`.
    Alpha,
}

/// Prefixes trainers put before the transformer's own module path.
const PREFIXES: [&str; 5] = [
    "base_model.model.",
    "model.diffusion_model.",
    "diffusion_model.",
    "transformer.",
    "model.",
];

/// Splits a key into its module path (prefix removed) and part, or `None` if the key is not a
/// LoRA tensor we know how to merge.
pub fn parse_key(key: &str) -> Option<(&str, Part)> {
    const SUFFIXES: [(&str, Part); 7] = [
        (".lora_A.weight", Part::Down),
        (".lora_A.default.weight", Part::Down),
        (".lora_down.weight", Part::Down),
        (".lora_B.weight", Part::Up),
        (".lora_B.default.weight", Part::Up),
        (".lora_up.weight", Part::Up),
        (".alpha", Part::Alpha),
    ];
    let (module, part) = SUFFIXES
        .iter()
        .find_map(|(suffix, part)| key.strip_suffix(suffix).map(|m| (m, *part)))?;
    let module = PREFIXES
        .iter()
        .find_map(|p| module.strip_prefix(p))
        .unwrap_or(module);
    (!module.is_empty()).then_some((module, part))
}

/// The diffusers name of a transformer module given in either convention.
pub fn to_diffusers(module: &str) -> String {
    let top_level = match module {
        "text_embedding.0" => Some("condition_embedder.text_embedder.linear_1"),
        "text_embedding.2" => Some("condition_embedder.text_embedder.linear_2"),
        "time_embedding.0" => Some("condition_embedder.time_embedder.linear_1"),
        "time_embedding.2" => Some("condition_embedder.time_embedder.linear_2"),
        "time_projection.1" => Some("condition_embedder.time_proj"),
        "head.head" => Some("proj_out"),
        _ => None,
    };
    if let Some(name) = top_level {
        return name.to_owned();
    }
    for blocks in ["blocks.", "vace_blocks."] {
        if let Some(rest) = module.strip_prefix(blocks)
            && let Some((index, inner)) = rest.split_once('.')
            && index.bytes().all(|b| b.is_ascii_digit())
        {
            return format!("{blocks}{index}.{}", block_module(inner));
        }
    }
    module.to_owned()
}

/// Inside one (main or VACE) block.
fn block_module(inner: &str) -> String {
    let renamed = match inner {
        "ffn.0" => "ffn.net.0.proj",
        "ffn.2" => "ffn.net.2",
        "before_proj" => "proj_in",
        "after_proj" => "proj_out",
        _ => {
            for (wan, diffusers) in [("self_attn.", "attn1."), ("cross_attn.", "attn2.")] {
                if let Some(projection) = inner.strip_prefix(wan) {
                    let to = match projection {
                        "q" => "to_q",
                        "k" => "to_k",
                        "v" => "to_v",
                        "o" => "to_out.0",
                        "k_img" => "add_k_proj",
                        "v_img" => "add_v_proj",
                        other => other,
                    };
                    return format!("{diffusers}{to}");
                }
            }
            inner
        }
    };
    renamed.to_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_of_both_conventions_parse_to_module_and_part() {
        assert_eq!(
            parse_key("diffusion_model.blocks.0.self_attn.q.lora_down.weight"),
            Some(("blocks.0.self_attn.q", Part::Down))
        );
        assert_eq!(
            parse_key("diffusion_model.blocks.0.self_attn.q.alpha"),
            Some(("blocks.0.self_attn.q", Part::Alpha))
        );
        assert_eq!(
            parse_key("base_model.model.blocks.1.attn2.to_out.0.lora_B.weight"),
            Some(("blocks.1.attn2.to_out.0", Part::Up))
        );
        assert_eq!(
            parse_key("transformer.vace_blocks.0.proj_in.lora_A.weight"),
            Some(("vace_blocks.0.proj_in", Part::Down))
        );
        assert_eq!(parse_key("blocks.0.norm3.diff_b"), None);
        assert_eq!(parse_key("lora_A.weight"), None);
    }

    #[test]
    fn wan_module_names_map_to_diffusers() {
        let cases = [
            ("blocks.0.self_attn.q", "blocks.0.attn1.to_q"),
            ("blocks.12.self_attn.k", "blocks.12.attn1.to_k"),
            ("blocks.3.self_attn.v", "blocks.3.attn1.to_v"),
            ("blocks.3.self_attn.o", "blocks.3.attn1.to_out.0"),
            ("blocks.3.cross_attn.q", "blocks.3.attn2.to_q"),
            ("blocks.3.cross_attn.o", "blocks.3.attn2.to_out.0"),
            ("blocks.3.cross_attn.k_img", "blocks.3.attn2.add_k_proj"),
            ("blocks.3.ffn.0", "blocks.3.ffn.net.0.proj"),
            ("blocks.3.ffn.2", "blocks.3.ffn.net.2"),
            ("vace_blocks.7.before_proj", "vace_blocks.7.proj_in"),
            ("vace_blocks.7.after_proj", "vace_blocks.7.proj_out"),
            ("vace_blocks.7.self_attn.q", "vace_blocks.7.attn1.to_q"),
            ("vace_blocks.7.ffn.2", "vace_blocks.7.ffn.net.2"),
            (
                "text_embedding.0",
                "condition_embedder.text_embedder.linear_1",
            ),
            (
                "time_embedding.2",
                "condition_embedder.time_embedder.linear_2",
            ),
            ("time_projection.1", "condition_embedder.time_proj"),
            ("head.head", "proj_out"),
            ("patch_embedding", "patch_embedding"),
            ("vace_patch_embedding", "vace_patch_embedding"),
        ];
        for (wan, diffusers) in cases {
            assert_eq!(to_diffusers(wan), diffusers, "{wan}");
        }
    }

    #[test]
    fn diffusers_names_pass_through_unchanged() {
        for name in [
            "blocks.0.attn1.to_q",
            "blocks.0.attn1.to_out.0",
            "blocks.0.ffn.net.0.proj",
            "blocks.0.ffn.net.2",
            "vace_blocks.0.proj_in",
            "vace_blocks.0.proj_out",
            "condition_embedder.time_proj",
            "proj_out",
        ] {
            assert_eq!(to_diffusers(name), name);
        }
    }
}
