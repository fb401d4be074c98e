//! LoRA adapters: reading them in either naming convention and merging them into the base weights.
//!
//! A LoRA adds `scale · B·A` to a weight `W` ([out, in]), with `A` ([r, in], "down") and `B`
//! ([out, r], "up"). The scale is `alpha / r` (`alpha / √r` for rsLoRA) times the user's scale:
//! - PEFT / diffusers files (`<module>.lora_A.weight`, `<module>.lora_B.weight`) take `alpha`
//!   (`lora_alpha`, `alpha_pattern`), `r` and `use_rslora` from the `adapter_config.json` next to
//!   them, or else from the copy diffusers' `save_lora_weights` puts in the safetensors header
//!   (`lora_adapter_metadata`);
//! - original-Wan files (`diffusion_model.<module>.lora_down.weight`, `lora_up.weight`) may carry a
//!   scalar `<module>.alpha`; without one (and without a config) alpha = r, scale 1.
//!
//! The merge happens once, at load: [`merge::merge_each`] computes `W + scale·B·A` in f32 for
//! every adapted module, a batch at a time, and the pipeline writes the results over the weights'
//! bytes in a copy of the model that ONNX Runtime then loads (`weights_session`: a scratch copy of
//! the external data, deleted once the session exists). Every key must land on an initializer of
//! the transformer with the right shape, or loading fails naming the key. A package can instead
//! have the LoRA merged in when it is exported (`python -m c4g.wan.export --lora`), before its
//! weights are rounded to f16.

pub mod merge;
pub mod names;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors};
use serde::Deserialize;

use crate::{RefinerError, Result};
use names::Part;

/// A LoRA to merge and how strongly.
#[derive(Debug, Clone, PartialEq)]
pub struct LoraSpec {
    /// The `.safetensors` file (a PEFT `adapter_config.json` next to it is read when present), or
    /// a directory holding `adapter_model.safetensors`. Either naming convention.
    pub path: PathBuf,
    /// Multiplies the file's own scale; 0 leaves the base model bit for bit.
    pub scale: f32,
}

/// The adapted modules of one LoRA file.
#[derive(Debug, Clone)]
pub struct Lora {
    path: PathBuf,
    modules: Vec<LoraModule>,
}

/// One adapted module: its low-rank factors and the file's scale for it.
#[derive(Debug, Clone, PartialEq)]
pub struct LoraModule {
    /// The module as the file names it (prefix removed), for messages.
    pub source: String,
    /// The module's diffusers name (the ONNX initializer is `<module>.weight`).
    pub module: String,
    /// `A`: `[r, in…]`.
    pub down: Vec<f32>,
    /// Shape of `down`.
    pub down_shape: Vec<usize>,
    /// `B`: `[out, r, 1…]`.
    pub up: Vec<f32>,
    /// Shape of `up`.
    pub up_shape: Vec<usize>,
    /// `alpha / r` (or `alpha / √r`), before the user's scale.
    pub scale: f32,
}

impl LoraModule {
    /// The rank `r`.
    pub fn rank(&self) -> usize {
        self.down_shape.first().copied().unwrap_or(0)
    }
}

/// The fields of PEFT's `adapter_config.json` that decide the scale.
#[derive(Debug, Clone, Default, Deserialize)]
struct AdapterConfig {
    r: Option<usize>,
    lora_alpha: Option<f64>,
    #[serde(default)]
    use_rslora: bool,
    #[serde(default)]
    use_dora: bool,
    #[serde(default)]
    fan_in_fan_out: bool,
    #[serde(default)]
    rank_pattern: BTreeMap<String, usize>,
    #[serde(default)]
    alpha_pattern: BTreeMap<String, f64>,
}

impl AdapterConfig {
    /// The value of `pattern` whose key names `module` (the whole name or a dotted suffix of it).
    fn pattern<T: Copy>(pattern: &BTreeMap<String, T>, module: &str) -> Option<T> {
        pattern
            .iter()
            .filter(|(k, _)| module == k.as_str() || module.ends_with(&format!(".{k}")))
            .max_by_key(|(k, _)| k.len())
            .map(|(_, v)| *v)
    }
}

impl Lora {
    /// Reads the LoRA at `path` (see [`LoraSpec::path`]).
    pub fn load(path: &Path) -> Result<Self> {
        let file = if path.is_dir() {
            path.join("adapter_model.safetensors")
        } else {
            path.to_path_buf()
        };
        let bytes = std::fs::read(&file).map_err(RefinerError::io(&file))?;
        let config_path = file.with_file_name("adapter_config.json");
        let config = if config_path.is_file() {
            Some(read_config(&config_path)?)
        } else {
            header_config(&file, &bytes)?
        };
        Self::from_bytes(&file, &bytes, config.as_ref())
    }

    /// The file read.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Adapted modules, sorted by diffusers name.
    pub fn modules(&self) -> &[LoraModule] {
        &self.modules
    }

    fn from_bytes(path: &Path, bytes: &[u8], config: Option<&AdapterConfig>) -> Result<Self> {
        let bad = |reason: String| RefinerError::Lora {
            path: path.to_path_buf(),
            reason,
        };
        if let Some(c) = config {
            if c.use_dora {
                return Err(bad(
                    "DoRA adapters (use_dora) cannot be merged as B·A".to_owned()
                ));
            }
            if c.fan_in_fan_out {
                return Err(bad(
                    "fan_in_fan_out adapters (transposed Conv1D weights) are not Wan LoRAs"
                        .to_owned(),
                ));
            }
        }
        let tensors = SafeTensors::deserialize(bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let mut parts: BTreeMap<String, Parts> = BTreeMap::new();
        for (key, view) in tensors.tensors() {
            let (module, part) = names::parse_key(&key).ok_or_else(|| {
                bad(format!(
                    "key {key:?} is not a LoRA tensor this refiner can merge (expected <module>.lora_A.weight / lora_B.weight, <module>.lora_down.weight / lora_up.weight or <module>.alpha)"
                ))
            })?;
            let values = to_f32(&view).map_err(|reason| bad(format!("key {key:?}: {reason}")))?;
            let entry = parts.entry(module.to_owned()).or_default();
            let slot = match part {
                Part::Down => &mut entry.down,
                Part::Up => &mut entry.up,
                Part::Alpha => &mut entry.alpha,
            };
            if slot.is_some() {
                return Err(bad(format!(
                    "module {module:?} has two {part:?} tensors (key {key:?})"
                )));
            }
            *slot = Some((key.clone(), view.shape().to_vec(), values));
        }
        let mut modules = parts
            .into_iter()
            .map(|(source, p)| p.into_module(source, config).map_err(&bad))
            .collect::<Result<Vec<_>>>()?;
        modules.sort_by(|a, b| a.module.cmp(&b.module));
        if let Some(w) = modules.windows(2).find(|w| w[0].module == w[1].module) {
            return Err(bad(format!(
                "modules {:?} and {:?} both adapt {}",
                w[0].source, w[1].source, w[0].module
            )));
        }
        if modules.is_empty() {
            return Err(bad("the file holds no LoRA tensors".to_owned()));
        }
        Ok(Self {
            path: path.to_path_buf(),
            modules,
        })
    }
}

fn read_config(path: &Path) -> Result<AdapterConfig> {
    let text = std::fs::read_to_string(path).map_err(RefinerError::io(path))?;
    serde_json::from_str(&text).map_err(|source| RefinerError::Json {
        path: path.to_path_buf(),
        source,
    })
}

/// The adapter config diffusers' `save_lora_weights` stores in the safetensors header
/// (`lora_adapter_metadata`, keys prefixed with the component, `transformer.r`, …), for files that
/// come without an `adapter_config.json`.
fn header_config(path: &Path, bytes: &[u8]) -> Result<Option<AdapterConfig>> {
    let bad = |reason: String| RefinerError::Lora {
        path: path.to_path_buf(),
        reason,
    };
    let (_, metadata) = SafeTensors::read_metadata(bytes)
        .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
    let Some(text) = metadata
        .metadata()
        .as_ref()
        .and_then(|m| m.get("lora_adapter_metadata"))
    else {
        return Ok(None);
    };
    let fields: serde_json::Map<String, serde_json::Value> =
        serde_json::from_str(text).map_err(|e| {
            bad(format!(
                "lora_adapter_metadata in the header is not a JSON object: {e}"
            ))
        })?;
    let unprefixed: serde_json::Map<String, serde_json::Value> = fields
        .into_iter()
        .map(|(k, v)| match k.strip_prefix("transformer.") {
            Some(field) => (field.to_owned(), v),
            None => (k, v),
        })
        .collect();
    serde_json::from_value(serde_json::Value::Object(unprefixed))
        .map(Some)
        .map_err(|e| bad(format!("lora_adapter_metadata in the header: {e}")))
}

type Tensor = (String, Vec<usize>, Vec<f32>);

/// The tensors found for one module.
#[derive(Default)]
struct Parts {
    down: Option<Tensor>,
    up: Option<Tensor>,
    alpha: Option<Tensor>,
}

impl Parts {
    fn into_module(
        self,
        source: String,
        config: Option<&AdapterConfig>,
    ) -> std::result::Result<LoraModule, String> {
        let (Some((down_key, down_shape, down)), Some((up_key, up_shape, up))) =
            (self.down, self.up)
        else {
            return Err(format!(
                "module {source:?} needs both a down (lora_A / lora_down) and an up (lora_B / lora_up) tensor"
            ));
        };
        let rank = down_shape.first().copied().unwrap_or(0);
        let shapes_fit = down_shape.len() >= 2
            && up_shape.len() == down_shape.len()
            && up_shape[1] == rank
            && rank > 0
            && up_shape[2..].iter().all(|&d| d == 1);
        if !shapes_fit {
            return Err(format!(
                "{down_key:?} {down_shape:?} and {up_key:?} {up_shape:?} are not a rank-r pair ([r, in…] and [out, r, 1…])"
            ));
        }
        let diffusers = names::to_diffusers(&source);
        let alpha = match (&self.alpha, config) {
            (Some((key, _, v)), _) => match v.as_slice() {
                [a] => f64::from(*a),
                _ => return Err(format!("{key:?} must hold one value, holds {}", v.len())),
            },
            (None, Some(c)) => {
                let configured_rank = AdapterConfig::pattern(&c.rank_pattern, &diffusers)
                    .or_else(|| AdapterConfig::pattern(&c.rank_pattern, &source))
                    .or(c.r);
                if let Some(r) = configured_rank
                    && r != rank
                {
                    return Err(format!(
                        "{down_key:?} has rank {rank} but adapter_config.json says r = {r}"
                    ));
                }
                AdapterConfig::pattern(&c.alpha_pattern, &diffusers)
                    .or_else(|| AdapterConfig::pattern(&c.alpha_pattern, &source))
                    .or(c.lora_alpha)
                    .unwrap_or(rank as f64)
            }
            (None, None) => rank as f64,
        };
        let rslora = config.is_some_and(|c| c.use_rslora);
        let denominator = if rslora {
            (rank as f64).sqrt()
        } else {
            rank as f64
        };
        Ok(LoraModule {
            source,
            module: diffusers,
            down,
            down_shape,
            up,
            up_shape,
            scale: (alpha / denominator) as f32,
        })
    }
}

fn to_f32(view: &safetensors::tensor::TensorView<'_>) -> std::result::Result<Vec<f32>, String> {
    let data = view.data();
    let values = match view.dtype() {
        Dtype::F32 => data
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect(),
        Dtype::F16 => data
            .chunks_exact(2)
            .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32())
            .collect(),
        Dtype::BF16 => data
            .chunks_exact(2)
            .map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32())
            .collect(),
        Dtype::F64 => data
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32)
            .collect(),
        other => return Err(format!("dtype {other:?} is not a floating-point type")),
    };
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;
    use safetensors::tensor::TensorView;

    fn file(tensors: &[(&str, Vec<usize>, Vec<f32>)]) -> Vec<u8> {
        file_with_metadata(tensors, None)
    }

    fn file_with_metadata(
        tensors: &[(&str, Vec<usize>, Vec<f32>)],
        metadata: Option<std::collections::HashMap<String, String>>,
    ) -> Vec<u8> {
        let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
            .iter()
            .map(|(k, s, v)| {
                (
                    (*k).to_owned(),
                    s.clone(),
                    v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                )
            })
            .collect();
        let views: Vec<(String, TensorView<'_>)> = bytes
            .iter()
            .map(|(k, s, b)| {
                (
                    k.clone(),
                    TensorView::new(Dtype::F32, s.clone(), b).unwrap(),
                )
            })
            .collect();
        safetensors::serialize(views, metadata).unwrap()
    }

    fn load(
        tensors: &[(&str, Vec<usize>, Vec<f32>)],
        config: Option<&AdapterConfig>,
    ) -> Result<Lora> {
        Lora::from_bytes(Path::new("test.safetensors"), &file(tensors), config)
    }

    fn pair(prefix: &str, down: &str, up: &str) -> Vec<(String, Vec<usize>, Vec<f32>)> {
        vec![
            (format!("{prefix}.{down}.weight"), vec![2, 3], vec![1.0; 6]),
            (format!("{prefix}.{up}.weight"), vec![4, 2], vec![1.0; 8]),
        ]
    }

    fn borrowed(v: &[(String, Vec<usize>, Vec<f32>)]) -> Vec<(&str, Vec<usize>, Vec<f32>)> {
        v.iter()
            .map(|(k, s, d)| (k.as_str(), s.clone(), d.clone()))
            .collect()
    }

    fn first(t: &[(String, Vec<usize>, Vec<f32>)], config: Option<&AdapterConfig>) -> LoraModule {
        load(&borrowed(t), config).unwrap().modules()[0].clone()
    }

    #[test]
    fn peft_scale_is_alpha_over_rank_from_the_config() {
        let t = pair("base_model.model.blocks.0.attn1.to_q", "lora_A", "lora_B");
        let config = AdapterConfig {
            r: Some(2),
            lora_alpha: Some(6.0),
            ..AdapterConfig::default()
        };
        let lora = load(&borrowed(&t), Some(&config)).unwrap();
        let m = &lora.modules()[0];
        assert_eq!(m.module, "blocks.0.attn1.to_q");
        assert_eq!((m.rank(), m.scale), (2, 3.0));

        let rs = AdapterConfig {
            use_rslora: true,
            ..config.clone()
        };
        let m = first(&t, Some(&rs));
        assert!((m.scale - 6.0 / 2f32.sqrt()).abs() < 1e-6);

        let patterned = AdapterConfig {
            alpha_pattern: [("attn1.to_q".to_owned(), 1.0)].into(),
            ..config.clone()
        };
        assert_eq!(
            load(&borrowed(&t), Some(&patterned)).unwrap().modules()[0].scale,
            0.5
        );

        let wrong_rank = AdapterConfig {
            r: Some(4),
            ..config
        };
        let err = load(&borrowed(&t), Some(&wrong_rank)).unwrap_err();
        assert!(err.to_string().contains("rank 2"), "{err}");
    }

    #[test]
    fn without_a_config_file_the_header_metadata_gives_the_scale() {
        let t = pair("transformer.blocks.0.attn1.to_q", "lora_A", "lora_B");
        let meta = r#"{"transformer.r": 2, "transformer.lora_alpha": 3.0, "transformer.use_rslora": false}"#;
        let bytes = file_with_metadata(
            &borrowed(&t),
            Some([("lora_adapter_metadata".to_owned(), meta.to_owned())].into()),
        );
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pytorch_lora_weights.safetensors");
        std::fs::write(&path, bytes).unwrap();
        let lora = Lora::load(&path).unwrap();
        assert_eq!(lora.modules()[0].scale, 1.5);
        // A config file next to it wins.
        std::fs::write(
            dir.path().join("adapter_config.json"),
            r#"{"r": 2, "lora_alpha": 8}"#,
        )
        .unwrap();
        assert_eq!(Lora::load(&path).unwrap().modules()[0].scale, 4.0);
        // A directory means its adapter_model.safetensors.
        std::fs::rename(&path, dir.path().join("adapter_model.safetensors")).unwrap();
        assert_eq!(Lora::load(dir.path()).unwrap().modules()[0].scale, 4.0);
    }

    #[test]
    fn wan_scale_comes_from_the_alpha_tensor_or_is_one() {
        let mut t = pair(
            "diffusion_model.blocks.1.self_attn.o",
            "lora_down",
            "lora_up",
        );
        let m = first(&t, None);
        assert_eq!(
            (m.module.as_str(), m.scale),
            ("blocks.1.attn1.to_out.0", 1.0)
        );
        t.push((
            "diffusion_model.blocks.1.self_attn.o.alpha".to_owned(),
            vec![],
            vec![1.0],
        ));
        let m = first(&t, None);
        assert_eq!(m.scale, 0.5);
    }

    #[test]
    fn incomplete_or_unknown_keys_are_errors_naming_the_key() {
        let t = pair(
            "diffusion_model.blocks.1.self_attn.o",
            "lora_down",
            "lora_up",
        );
        let err = load(&borrowed(&t[..1]), None).unwrap_err();
        assert!(err.to_string().contains("blocks.1.self_attn.o"), "{err}");

        let mut t2 = t.clone();
        t2.push((
            "diffusion_model.blocks.1.norm3.diff_b".to_owned(),
            vec![2],
            vec![0.0; 2],
        ));
        let err = load(&borrowed(&t2), None).unwrap_err();
        assert!(err.to_string().contains("blocks.1.norm3.diff_b"), "{err}");

        let bad_rank = vec![
            ("m.lora_A.weight", vec![2, 3], vec![0.0; 6]),
            ("m.lora_B.weight", vec![4, 3], vec![0.0; 12]),
        ];
        let err = load(&bad_rank, None).unwrap_err();
        assert!(err.to_string().contains("m.lora_A.weight"), "{err}");
    }

    #[test]
    fn the_same_module_named_twice_is_an_error() {
        let mut t = pair(
            "diffusion_model.blocks.0.self_attn.q",
            "lora_down",
            "lora_up",
        );
        t.extend(pair("blocks.0.attn1.to_q", "lora_A", "lora_B"));
        let err = load(&borrowed(&t), None).unwrap_err();
        assert!(err.to_string().contains("blocks.0.attn1.to_q"), "{err}");
    }
}
