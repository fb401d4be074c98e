//! Reading the initializers (weights) of an ONNX file, for merging a LoRA into them.
//!
//! ONNX Runtime does not hand a model's initializers back, so we read the protobuf ourselves. Only
//! the few fields on the path `ModelProto.graph.initializer` are declared; prost skips everything
//! else (nodes, attributes, metadata) without decoding it. Tensor bytes stay slices of the file's
//! buffer until asked for, and external data (`data_location = EXTERNAL`, required above 2 GiB) is
//! read from its side file on demand, so a 4 GiB model costs nothing until a weight is merged.
//!
//! The same bookkeeping lets [`OnnxWeights::patched`] write merged weights over the bytes of
//! embedded initializers in an in-memory copy of the model (see `runtime` for why).

use std::collections::HashMap;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Component, Path, PathBuf};

use prost::Message;
use prost::bytes::Bytes;

use crate::{RefinerError, Result};

// Field numbers from onnx.proto (onnx/onnx, IR version 10+).
#[derive(Clone, PartialEq, Message)]
struct ModelProto {
    #[prost(message, optional, tag = "7")]
    graph: Option<GraphProto>,
}

#[derive(Clone, PartialEq, Message)]
struct GraphProto {
    #[prost(message, repeated, tag = "5")]
    initializer: Vec<TensorProto>,
}

#[derive(Clone, PartialEq, Message)]
struct TensorProto {
    #[prost(int64, repeated, tag = "1")]
    dims: Vec<i64>,
    #[prost(int32, tag = "2")]
    data_type: i32,
    #[prost(float, repeated, tag = "4")]
    float_data: Vec<f32>,
    // FLOAT16 and BFLOAT16 values live here as their 16 bits, one per int32, when not raw.
    #[prost(int32, repeated, tag = "5")]
    int32_data: Vec<i32>,
    #[prost(string, tag = "8")]
    name: String,
    #[prost(bytes = "bytes", tag = "9")]
    raw_data: Bytes,
    #[prost(message, repeated, tag = "13")]
    external_data: Vec<StringStringEntryProto>,
    #[prost(int32, tag = "14")]
    data_location: i32,
}

#[derive(Clone, PartialEq, Message)]
struct StringStringEntryProto {
    #[prost(string, tag = "1")]
    key: String,
    #[prost(string, tag = "2")]
    value: String,
}

const DATA_LOCATION_EXTERNAL: i32 = 1;

/// Element types of floating-point initializers we can merge into.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ElementType {
    /// IEEE float32 (ONNX `FLOAT`).
    F32,
    /// IEEE float16 (ONNX `FLOAT16`).
    F16,
    /// bfloat16 (ONNX `BFLOAT16`).
    Bf16,
}

impl ElementType {
    fn from_onnx(code: i32) -> Option<Self> {
        match code {
            1 => Some(Self::F32),
            10 => Some(Self::F16),
            16 => Some(Self::Bf16),
            _ => None,
        }
    }

    fn size(self) -> usize {
        match self {
            Self::F32 => 4,
            Self::F16 | Self::Bf16 => 2,
        }
    }
}

/// Where an initializer's bytes are.
#[derive(Debug, Clone)]
enum Storage {
    /// Little-endian bytes inside the model file, at `offset`.
    Raw { offset: usize, len: usize },
    /// Little-endian bytes that could not be located in the file's buffer.
    Detached(Bytes),
    /// `float_data`.
    Floats(Vec<f32>),
    /// `int32_data` holding 16-bit values.
    Halves(Vec<i32>),
    /// A side file next to the model.
    External {
        location: String,
        offset: u64,
        length: Option<u64>,
    },
}

/// One initializer: its shape, type, and where its values are.
#[derive(Debug, Clone)]
pub struct Initializer {
    name: String,
    dims: Vec<usize>,
    data_type: i32,
    storage: Storage,
}

impl Initializer {
    /// The initializer's name in the graph.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Its shape.
    pub fn dims(&self) -> &[usize] {
        &self.dims
    }

    /// Its element type, if it is one we can merge into.
    pub fn element_type(&self) -> Option<ElementType> {
        ElementType::from_onnx(self.data_type)
    }

    fn len(&self) -> usize {
        self.dims.iter().product()
    }

    /// True when the values live in a side file (`data_location = EXTERNAL`).
    pub fn is_external(&self) -> bool {
        matches!(self.storage, Storage::External { .. })
    }

    /// Where in a side file the values live: the file (relative to the model's folder) and the
    /// byte offset.
    pub fn external_location(&self) -> Option<(&str, u64)> {
        match &self.storage {
            Storage::External {
                location, offset, ..
            } => Some((location, *offset)),
            _ => None,
        }
    }
}

/// `location` (an external-data file named by a model) as a path under the model's folder:
/// relative, with no `..`, as ONNX Runtime also requires, so that reading or writing it never
/// leaves that folder.
pub fn external_path(model: &Path, location: &str) -> Result<PathBuf> {
    let relative = Path::new(location);
    let inside = !location.is_empty()
        && relative
            .components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    if !inside {
        return Err(RefinerError::Onnx {
            path: model.to_path_buf(),
            reason: format!(
                "external data location {location:?} is not a relative path inside the model's folder"
            ),
        });
    }
    Ok(relative.to_path_buf())
}

/// The initializers of one `.onnx` file, by name.
#[derive(Debug, Clone)]
pub struct OnnxWeights {
    path: PathBuf,
    bytes: Bytes,
    initializers: HashMap<String, Initializer>,
}

impl OnnxWeights {
    /// Reads the initializer table of `path` (values stay where they are until asked for).
    pub fn open(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(RefinerError::io(path))?;
        Self::from_bytes(path, Bytes::from(bytes))
    }

    fn from_bytes(path: &Path, bytes: Bytes) -> Result<Self> {
        let bad = |reason: String| RefinerError::Onnx {
            path: path.to_path_buf(),
            reason,
        };
        // Decoding from `Bytes` hands out `raw_data` as slices of this same buffer, which is how
        // an initializer's offset in the file is known.
        let model = ModelProto::decode(bytes.clone())
            .map_err(|e| bad(format!("not an ONNX model protobuf: {e}")))?;
        let graph = model
            .graph
            .ok_or_else(|| bad("the model has no graph".to_owned()))?;
        let mut initializers = HashMap::with_capacity(graph.initializer.len());
        for t in graph.initializer {
            let init = initializer(t, &bytes).map_err(&bad)?;
            initializers.insert(init.name.clone(), init);
        }
        Ok(Self {
            path: path.to_path_buf(),
            bytes,
            initializers,
        })
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The initializer called `name`.
    pub fn get(&self, name: &str) -> Option<&Initializer> {
        self.initializers.get(name)
    }

    /// Every initializer name, sorted.
    pub fn names(&self) -> Vec<&str> {
        let mut names: Vec<&str> = self.initializers.keys().map(String::as_str).collect();
        names.sort_unstable();
        names
    }

    /// The side files the initializers' values live in (`location`s), sorted.
    pub fn external_locations(&self) -> Vec<&str> {
        let mut locations: Vec<&str> = self
            .initializers
            .values()
            .filter_map(|i| i.external_location().map(|(location, _)| location))
            .collect();
        locations.sort_unstable();
        locations.dedup();
        locations
    }

    /// The values of `init` as f32 (fp16 and bf16 widen exactly).
    pub fn read_f32(&self, init: &Initializer) -> Result<Vec<f32>> {
        let bad = |reason: String| RefinerError::Onnx {
            path: self.path.clone(),
            reason: format!("initializer {:?}: {reason}", init.name),
        };
        let ty = init.element_type().ok_or_else(|| {
            bad(format!(
                "element type {} is not a floating-point type we can merge into (float32, float16, bfloat16)",
                init.data_type
            ))
        })?;
        let n = init.len();
        let values = match &init.storage {
            Storage::Floats(v) if ty == ElementType::F32 => v.clone(),
            Storage::Halves(v) => v.iter().map(|&h| widen(ty, h as u16)).collect(),
            Storage::Raw { offset, len } => decode_le(ty, &self.bytes[*offset..*offset + *len]),
            Storage::Detached(bytes) => decode_le(ty, bytes),
            Storage::External {
                location,
                offset,
                length,
            } => {
                let bytes = self.read_external(
                    location,
                    *offset,
                    length.unwrap_or((n * ty.size()) as u64),
                )?;
                decode_le(ty, &bytes)
            }
            Storage::Floats(_) => return Err(bad("float_data in a non-float32 tensor".to_owned())),
        };
        if values.len() != n {
            return Err(bad(format!(
                "holds {} values, its shape {:?} needs {n}",
                values.len(),
                init.dims
            )));
        }
        Ok(values)
    }

    /// A copy of the model file with each of `replacements` (name, little-endian bytes) written
    /// over the bytes of its embedded initializer; the sizes must match exactly.
    pub fn patched<'r>(
        &self,
        replacements: impl IntoIterator<Item = (&'r str, Vec<u8>)>,
    ) -> Result<Vec<u8>> {
        let mut out = self.bytes.to_vec();
        for (name, bytes) in replacements {
            let bad = |reason: String| RefinerError::Onnx {
                path: self.path.clone(),
                reason: format!("initializer {name:?}: {reason}"),
            };
            let init = self
                .get(name)
                .ok_or_else(|| bad("not in the model".to_owned()))?;
            let Storage::Raw { offset, len } = init.storage else {
                return Err(bad(
                    "its values are not raw_data inside the model file, so they cannot be replaced in place (re-export it with raw_data)"
                        .to_owned(),
                ));
            };
            if bytes.len() != len {
                return Err(bad(format!(
                    "{} replacement bytes for {len} in the model",
                    bytes.len()
                )));
            }
            out[offset..offset + len].copy_from_slice(&bytes);
        }
        Ok(out)
    }

    fn read_external(&self, location: &str, offset: u64, length: u64) -> Result<Vec<u8>> {
        let dir = self.path.parent().unwrap_or(Path::new("."));
        let file_path = dir.join(external_path(&self.path, location)?);
        let io = RefinerError::io(&file_path);
        let mut file = File::open(&file_path).map_err(RefinerError::io(&file_path))?;
        file.seek(SeekFrom::Start(offset))
            .map_err(RefinerError::io(&file_path))?;
        let mut buf = vec![0u8; usize::try_from(length).unwrap_or(usize::MAX)];
        file.read_exact(&mut buf).map_err(io)?;
        Ok(buf)
    }
}

fn initializer(t: TensorProto, file: &Bytes) -> std::result::Result<Initializer, String> {
    let dims = t
        .dims
        .iter()
        .map(|&d| {
            usize::try_from(d).map_err(|_| format!("initializer {:?} has dimension {d}", t.name))
        })
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let storage = if t.data_location == DATA_LOCATION_EXTERNAL {
        let entry = |key: &str| {
            t.external_data
                .iter()
                .find(|e| e.key == key)
                .map(|e| e.value.clone())
        };
        let number = |key: &str| -> std::result::Result<Option<u64>, String> {
            entry(key)
                .map(|v| {
                    v.parse::<u64>()
                        .map_err(|_| format!("initializer {:?}: external {key} {v:?}", t.name))
                })
                .transpose()
        };
        Storage::External {
            location: entry("location")
                .ok_or_else(|| format!("initializer {:?} is external with no location", t.name))?,
            offset: number("offset")?.unwrap_or(0),
            length: number("length")?,
        }
    } else if !t.raw_data.is_empty() {
        let start = file.as_ptr() as usize;
        let at = t.raw_data.as_ptr() as usize;
        let len = t.raw_data.len();
        if at >= start && at + len <= start + file.len() {
            Storage::Raw {
                offset: at - start,
                len,
            }
        } else {
            Storage::Detached(t.raw_data)
        }
    } else if !t.float_data.is_empty() {
        Storage::Floats(t.float_data)
    } else {
        Storage::Halves(t.int32_data)
    };
    Ok(Initializer {
        name: t.name,
        dims,
        data_type: t.data_type,
        storage,
    })
}

fn widen(ty: ElementType, bits: u16) -> f32 {
    match ty {
        ElementType::F16 => half::f16::from_bits(bits).to_f32(),
        ElementType::Bf16 => half::bf16::from_bits(bits).to_f32(),
        ElementType::F32 => f32::NAN,
    }
}

fn decode_le(ty: ElementType, bytes: &[u8]) -> Vec<f32> {
    match ty {
        ElementType::F32 => bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect(),
        ElementType::F16 | ElementType::Bf16 => bytes
            .chunks_exact(2)
            .map(|b| widen(ty, u16::from_le_bytes([b[0], b[1]])))
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tensor(name: &str, dims: &[i64], data_type: i32) -> TensorProto {
        TensorProto {
            dims: dims.to_vec(),
            data_type,
            name: name.to_owned(),
            ..TensorProto::default()
        }
    }

    fn model(initializers: Vec<TensorProto>) -> Bytes {
        let m = ModelProto {
            graph: Some(GraphProto {
                initializer: initializers,
            }),
        };
        Bytes::from(m.encode_to_vec())
    }

    #[test]
    fn raw_float_and_half_initializers_read_back_as_f32() {
        let mut raw = tensor("w.raw", &[2, 2], 1);
        raw.raw_data = [1.0f32, -2.0, 0.5, 3.25]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>()
            .into();
        let mut floats = tensor("w.floats", &[3], 1);
        floats.float_data = vec![0.25, 0.5, 0.75];
        let mut halves = tensor("w.f16", &[2], 10);
        halves.int32_data = vec![
            i32::from(half::f16::from_f32(1.5).to_bits()),
            i32::from(half::f16::from_f32(-0.125).to_bits()),
        ];
        let mut bf = tensor("w.bf16", &[1], 16);
        bf.raw_data = half::bf16::from_f32(2.0).to_le_bytes().to_vec().into();
        let w = OnnxWeights::from_bytes(Path::new("m.onnx"), model(vec![raw, floats, halves, bf]))
            .unwrap();
        assert_eq!(w.names(), vec!["w.bf16", "w.f16", "w.floats", "w.raw"]);
        let read = |n: &str| w.read_f32(w.get(n).unwrap()).unwrap();
        assert_eq!(read("w.raw"), vec![1.0, -2.0, 0.5, 3.25]);
        assert_eq!(read("w.floats"), vec![0.25, 0.5, 0.75]);
        assert_eq!(read("w.f16"), vec![1.5, -0.125]);
        assert_eq!(read("w.bf16"), vec![2.0]);
        assert_eq!(w.get("w.raw").unwrap().dims(), &[2, 2]);
        assert_eq!(
            w.get("w.f16").unwrap().element_type(),
            Some(ElementType::F16)
        );
    }

    #[test]
    fn patching_replaces_exactly_the_initializers_bytes() {
        let mut a = tensor("a", &[2], 1);
        a.raw_data = [1.0f32, 2.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>()
            .into();
        let mut b = tensor("b", &[1], 1);
        b.raw_data = 3.0f32.to_le_bytes().to_vec().into();
        let mut floats = tensor("c", &[1], 1);
        floats.float_data = vec![4.0];
        let w = OnnxWeights::from_bytes(Path::new("m.onnx"), model(vec![a, b, floats])).unwrap();
        let new_a: Vec<u8> = [5.0f32, 6.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let patched = w.patched([("a", new_a)]).unwrap();
        let p = OnnxWeights::from_bytes(Path::new("m.onnx"), Bytes::from(patched)).unwrap();
        assert_eq!(p.read_f32(p.get("a").unwrap()).unwrap(), vec![5.0, 6.0]);
        assert_eq!(p.read_f32(p.get("b").unwrap()).unwrap(), vec![3.0]);
        assert!(w.patched([("a", vec![0u8; 4])]).is_err());
        assert!(w.patched([("c", vec![0u8; 4])]).is_err());
        assert!(w.patched([("zz", vec![0u8; 4])]).is_err());
    }

    #[test]
    fn external_data_is_read_from_the_side_file() {
        let dir = tempfile::tempdir().unwrap();
        let values = [7.0f32, 8.0, 9.0];
        let mut side = vec![0u8; 16];
        side.extend(values.iter().flat_map(|v| v.to_le_bytes()));
        std::fs::write(dir.path().join("weights.bin"), side).unwrap();
        let mut t = tensor("ext", &[3], 1);
        t.data_location = DATA_LOCATION_EXTERNAL;
        t.external_data = [
            ("location", "weights.bin"),
            ("offset", "16"),
            ("length", "12"),
        ]
        .iter()
        .map(|(k, v)| StringStringEntryProto {
            key: (*k).to_owned(),
            value: (*v).to_owned(),
        })
        .collect();
        let path = dir.path().join("m.onnx");
        std::fs::write(&path, model(vec![t])).unwrap();
        let w = OnnxWeights::open(&path).unwrap();
        assert!(w.get("ext").unwrap().is_external());
        assert_eq!(w.read_f32(w.get("ext").unwrap()).unwrap(), values.to_vec());
    }

    #[test]
    fn a_short_tensor_and_a_non_float_tensor_are_errors() {
        let mut short = tensor("short", &[4], 1);
        short.float_data = vec![1.0];
        let ints = tensor("ints", &[1], 7);
        let w = OnnxWeights::from_bytes(Path::new("m.onnx"), model(vec![short, ints])).unwrap();
        let err = w.read_f32(w.get("short").unwrap()).unwrap_err();
        assert!(err.to_string().contains("short"), "{err}");
        assert!(w.read_f32(w.get("ints").unwrap()).is_err());
    }

    #[test]
    fn external_locations_stay_inside_the_models_folder() {
        let model = Path::new("/pkg/transformer.onnx");
        assert_eq!(
            external_path(model, "weights/transformer.onnx.data").unwrap(),
            Path::new("weights/transformer.onnx.data")
        );
        for bad in ["", "../x.data", "/etc/passwd", "a/../../x", "./x/../../y"] {
            let err = external_path(model, bad).unwrap_err().to_string();
            assert!(err.contains("inside the model's folder"), "{bad:?}: {err}");
        }
    }

    #[test]
    fn garbage_is_not_a_model() {
        let err = OnnxWeights::from_bytes(Path::new("m.onnx"), Bytes::from_static(b"\xff\xff\xff"))
            .unwrap_err();
        assert!(matches!(err, RefinerError::Onnx { .. }), "{err}");
    }
}
