//! The 3D Gaussian splatting `.ply`: one `vertex` element per Gaussian.
//!
//! Written as `binary_little_endian`, float properties in the order trainers use:
//! `x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3`,
//! then `feat_0 .. feat_{F-1}` when the set has features. Values are stored *before* activation,
//! as trainers keep them:
//! - opacity as its logit `ln(o / (1 − o))`, with `o` clamped to `[1e-7, 1 − 1e-7]` so the file
//!   holds no infinities;
//! - scales as their logarithm, with scales clamped below at `1e-30` (so zero stays finite);
//! - colour as the degree-0 spherical-harmonic coefficient `f_dc = (rgb − 0.5) / C0`,
//!   `C0 = 0.28209479` (higher degrees, `f_rest_*`, are not written and are ignored when read);
//! - the rotation quaternion as `rot_0..3 = w, x, y, z`; normals as zeros.
//!
//! Round trip through [`encode`] and [`decode`]: positions, features exact; rotations within 1e-6
//! (the reader normalises, as the 3DGS activation does); opacity within 1e-6 absolute; colour
//! within 1e-6 absolute; scales within 2e-6 relative (above 1e-30).
//!
//! Reading accepts what other writers produce: `ascii`, `binary_little_endian` and
//! `binary_big_endian`; properties in any order and of any scalar type; extra properties
//! (`f_rest_*`, normals, anything else) ignored; other elements before or after `vertex` (list
//! properties included) skipped. Truncated or malformed input fails with an error saying where.

use std::path::Path;

use c4g_scene::{FeatureBlock, GaussianSet, SceneError};

/// The degree-0 spherical-harmonic constant, `1 / (2 √π)`.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// Opacities are clamped to `[OPACITY_EPS, 1 − OPACITY_EPS]` before the logit.
pub const OPACITY_EPS: f64 = 1e-7;
/// Scales are clamped below at this before the logarithm.
pub const SCALE_MIN: f64 = 1e-30;

const REQUIRED: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
];

/// Reads a `.ply` file.
pub fn read(path: &Path) -> Result<GaussianSet, SceneError> {
    decode(&super::read_file(path)?)
}

/// Writes `set` to a `.ply` file.
pub fn write(path: &Path, set: &GaussianSet) -> Result<(), SceneError> {
    super::write_file(path, &encode(set))
}

/// The `.ply` bytes of `set` (binary little endian).
pub fn encode(set: &GaussianSet) -> Vec<u8> {
    let channels = set.features().map_or(0, |f| f.width());
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by c4g-renderer\nelement vertex {}\n",
        set.len()
    );
    let names = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    ]
    .into_iter()
    .map(str::to_owned)
    .chain(
        [
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ]
        .map(str::to_owned),
    )
    .chain((0..channels).map(|k| format!("feat_{k}")));
    for name in names {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");

    let mut out = header.into_bytes();
    out.reserve(set.len() * (17 + channels) * 4);
    let mut push = |v: f32| out.extend_from_slice(&v.to_le_bytes());
    for i in 0..set.len() {
        let [x, y, z] = set.positions()[i];
        let [r, g, b] = set.colors()[i];
        for v in [x, y, z, 0.0, 0.0, 0.0] {
            push(v);
        }
        for c in [r, g, b] {
            push(((f64::from(c) - 0.5) / SH_C0) as f32);
        }
        push(logit(set.opacities()[i]));
        for s in set.scales()[i] {
            push(f64::from(s).max(SCALE_MIN).ln() as f32);
        }
        for q in set.rotations()[i] {
            push(q);
        }
        if let Some(row) = set.features().and_then(|f| f.row(i)) {
            for &v in row {
                push(v);
            }
        }
    }
    out
}

/// Parses `.ply` bytes into a Gaussian set (activated: sigmoid opacity, exp scale, RGB from the
/// degree-0 coefficient, normalised rotation).
pub fn decode(bytes: &[u8]) -> Result<GaussianSet, SceneError> {
    let (header, body_start) = Header::parse(bytes)?;
    let mut body = Body {
        bytes,
        pos: body_start,
        encoding: header.encoding,
    };
    let mut vertices = None;
    for element in &header.elements {
        if element.name == "vertex" {
            vertices = Some(read_vertices(element, &mut body)?);
            // Nothing after the vertices is needed.
            break;
        }
        body.skip_element(element)?;
    }
    vertices.ok_or_else(|| format_error("no `vertex` element"))
}

fn read_vertices(element: &Element, body: &mut Body) -> Result<GaussianSet, SceneError> {
    let column = |name: &str| element.properties.iter().position(|p| p.name == name);
    let mut required = [0usize; 14];
    for (slot, name) in required.iter_mut().zip(REQUIRED) {
        *slot = column(name)
            .ok_or_else(|| format_error(format!("the vertex element has no `{name}` property")))?;
    }
    let feature_columns: Vec<usize> = (0..).map_while(|k| column(&format!("feat_{k}"))).collect();
    if let Some(p) = element.properties.iter().find(|p| p.list.is_some()) {
        return Err(format_error(format!(
            "vertex property `{}` is a list; Gaussians have scalar properties",
            p.name
        )));
    }
    if body.encoding != Encoding::Ascii {
        let stride: usize = element.properties.iter().map(|p| p.kind.size()).sum();
        let need = stride.checked_mul(element.count);
        let have = body.bytes.len() - body.pos;
        if need.is_none_or(|need| need > have) {
            return Err(format_error(format!(
                "truncated: {} vertices of {stride} bytes need {} bytes, the file has {have} left",
                element.count,
                need.map_or_else(|| "more than addressable".to_owned(), |n| n.to_string())
            )));
        }
    }

    let n = element.count;
    // An ascii value takes at least two bytes: a count the file cannot hold allocates nothing.
    let cap = n.min((body.bytes.len() - body.pos) / (2 * element.properties.len()).max(1));
    let (mut positions, mut scales, mut rotations, mut opacities, mut colors) = (
        Vec::with_capacity(cap),
        Vec::with_capacity(cap),
        Vec::with_capacity(cap),
        Vec::with_capacity(cap),
        Vec::with_capacity(cap),
    );
    let mut features = Vec::with_capacity(cap * feature_columns.len());
    let mut row = vec![0f64; element.properties.len()];
    for v in 0..n {
        body.read_row(element, &mut row)
            .map_err(|e| format_error(format!("vertex {v}: {e}")))?;
        let r = |k: usize| row[required[k]];
        positions.push([r(0) as f32, r(1) as f32, r(2) as f32]);
        colors.push([3, 4, 5].map(|k| (r(k) * SH_C0 + 0.5) as f32));
        opacities.push(sigmoid(r(6)) as f32);
        scales.push([7, 8, 9].map(|k| r(k).exp() as f32));
        rotations.push(normalized([r(10), r(11), r(12), r(13)]));
        features.extend(feature_columns.iter().map(|&c| row[c] as f32));
    }
    let set = GaussianSet::new(positions, scales, rotations, opacities, colors)?;
    if feature_columns.is_empty() {
        Ok(set)
    } else {
        set.with_features(FeatureBlock::new(feature_columns.len(), features)?)
    }
}

fn logit(opacity: f32) -> f32 {
    let o = f64::from(opacity).clamp(OPACITY_EPS, 1.0 - OPACITY_EPS);
    // NaN passes through clamp and stays NaN: the file keeps what the set held.
    (o / (1.0 - o)).ln() as f32
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

fn normalized(q: [f64; 4]) -> [f32; 4] {
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm > 0.0 && norm.is_finite() {
        q.map(|v| (v / norm) as f32)
    } else {
        q.map(|v| v as f32)
    }
}

fn format_error(reason: impl Into<String>) -> SceneError {
    SceneError::Format {
        format: "ply",
        reason: reason.into(),
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Encoding {
    Ascii,
    LittleEndian,
    BigEndian,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Kind {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    fn decode(self, b: &[u8], big: bool) -> f64 {
        macro_rules! num {
            ($t:ty, $n:literal) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                f64::from(if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                })
            }};
        }
        match self {
            Self::I8 => num!(i8, 1),
            Self::U8 => num!(u8, 1),
            Self::I16 => num!(i16, 2),
            Self::U16 => num!(u16, 2),
            Self::I32 => num!(i32, 4),
            Self::U32 => num!(u32, 4),
            Self::F32 => num!(f32, 4),
            Self::F64 => num!(f64, 8),
        }
    }
}

#[derive(Debug)]
struct Property {
    name: String,
    kind: Kind,
    /// The count's type, for list properties.
    list: Option<Kind>,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

#[derive(Debug)]
struct Header {
    encoding: Encoding,
    elements: Vec<Element>,
}

impl Header {
    /// The header and the offset of the first body byte.
    fn parse(bytes: &[u8]) -> Result<(Self, usize), SceneError> {
        // Header lines up to and including `end_header`, and the offset just past it.
        let mut lines = Vec::new();
        let mut start = 0;
        let body_start = loop {
            let Some(len) = bytes[start..].iter().position(|&b| b == b'\n') else {
                return Err(format_error(
                    "no `end_header` line: not a PLY file, or truncated in the header",
                ));
            };
            let line = std::str::from_utf8(&bytes[start..start + len])
                .map_err(|_| format_error(format!("header line {} is not text", lines.len() + 1)))?
                .trim();
            start += len + 1;
            if line == "end_header" {
                break start;
            }
            lines.push(line);
        };
        let mut lines = lines.into_iter().enumerate().map(|(i, l)| (i + 1, l));
        match lines.next() {
            Some((_, "ply")) => {}
            _ => return Err(format_error("the file does not start with `ply`")),
        }
        let mut encoding = None;
        let mut elements: Vec<Element> = Vec::new();
        for (line_no, line) in lines {
            let words: Vec<&str> = line.split_whitespace().collect();
            let bad = |what: &str| format_error(format!("header line {line_no} `{line}`: {what}"));
            match words.as_slice() {
                [] | ["comment", ..] | ["obj_info", ..] => {}
                ["format", kind, _version] => {
                    encoding = Some(match *kind {
                        "ascii" => Encoding::Ascii,
                        "binary_little_endian" => Encoding::LittleEndian,
                        "binary_big_endian" => Encoding::BigEndian,
                        _ => return Err(bad("unknown format")),
                    });
                }
                ["element", name, count] => elements.push(Element {
                    name: (*name).to_owned(),
                    count: count
                        .parse()
                        .map_err(|_| bad("the count is not a number"))?,
                    properties: Vec::new(),
                }),
                ["property", "list", count_kind, kind, name] => {
                    let element = elements
                        .last_mut()
                        .ok_or_else(|| bad("a property before any element"))?;
                    element.properties.push(Property {
                        name: (*name).to_owned(),
                        kind: Kind::parse(kind).ok_or_else(|| bad("unknown type"))?,
                        list: Some(Kind::parse(count_kind).ok_or_else(|| bad("unknown type"))?),
                    });
                }
                ["property", kind, name] => {
                    let element = elements
                        .last_mut()
                        .ok_or_else(|| bad("a property before any element"))?;
                    element.properties.push(Property {
                        name: (*name).to_owned(),
                        kind: Kind::parse(kind).ok_or_else(|| bad("unknown type"))?,
                        list: None,
                    });
                }
                _ => return Err(bad("not a header line this reader knows")),
            }
        }
        let encoding = encoding.ok_or_else(|| format_error("the header has no `format` line"))?;
        Ok((Self { encoding, elements }, body_start))
    }
}

/// A cursor over the body.
struct Body<'a> {
    bytes: &'a [u8],
    pos: usize,
    encoding: Encoding,
}

impl Body<'_> {
    /// One scalar of type `kind`.
    fn scalar(&mut self, kind: Kind) -> Result<f64, String> {
        match self.encoding {
            Encoding::Ascii => {
                let token = self.token().ok_or("the file ends in the middle of a row")?;
                token
                    .parse::<f64>()
                    .map_err(|_| format!("`{token}` is not a number"))
            }
            Encoding::LittleEndian | Encoding::BigEndian => {
                let end = self.pos + kind.size();
                let b = self
                    .bytes
                    .get(self.pos..end)
                    .ok_or("the file ends in the middle of a row")?;
                self.pos = end;
                Ok(kind.decode(b, self.encoding == Encoding::BigEndian))
            }
        }
    }

    /// The next whitespace-separated token (ascii).
    fn token(&mut self) -> Option<&str> {
        let rest = &self.bytes[self.pos..];
        let start = rest.iter().position(|b| !b.is_ascii_whitespace())?;
        let len = rest[start..]
            .iter()
            .position(|b| b.is_ascii_whitespace())
            .unwrap_or(rest.len() - start);
        self.pos += start + len;
        std::str::from_utf8(&rest[start..start + len]).ok()
    }

    /// One row of scalar properties into `row`.
    fn read_row(&mut self, element: &Element, row: &mut [f64]) -> Result<(), String> {
        for (slot, p) in row.iter_mut().zip(&element.properties) {
            *slot = self.scalar(p.kind)?;
        }
        Ok(())
    }

    fn skip_element(&mut self, element: &Element) -> Result<(), SceneError> {
        for i in 0..element.count {
            for p in &element.properties {
                let items = match p.list {
                    Some(count_kind) => {
                        let n = self
                            .scalar(count_kind)
                            .map_err(|e| skip_error(element, i, &e))?;
                        if !(n >= 0.0 && n.fract() == 0.0) {
                            return Err(skip_error(element, i, "a list length is not a count"));
                        }
                        n as usize
                    }
                    None => 1,
                };
                for _ in 0..items {
                    self.scalar(p.kind)
                        .map_err(|e| skip_error(element, i, &e))?;
                }
            }
        }
        Ok(())
    }
}

fn skip_error(element: &Element, index: usize, reason: &str) -> SceneError {
    format_error(format!("{} {index}: {reason}", element.name))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(features: bool) -> GaussianSet {
        let set = GaussianSet::new(
            vec![[0.1, -2.0, 3.5], [1e-3, 4e4, -7.25], [0.0, 0.0, 0.0]],
            vec![[0.01, 0.2, 3.0], [1e-6, 1e5, 0.5], [0.0, 1.0, 2.0]],
            vec![
                [1.0, 0.0, 0.0, 0.0],
                [0.5, 0.5, -0.5, 0.5],
                [0.0, 0.6, 0.0, 0.8],
            ],
            vec![0.5, 1.0, 0.0],
            vec![[0.0, 0.5, 1.0], [0.25, 0.75, 0.125], [1.5, 0.0, 0.3]],
        )
        .unwrap();
        if features {
            let values = (0..3 * 4).map(|i| i as f32 * 0.37 - 1.0).collect();
            set.with_features(FeatureBlock::new(4, values).unwrap())
                .unwrap()
        } else {
            set
        }
    }

    fn assert_close(a: &GaussianSet, b: &GaussianSet) {
        assert_eq!(a.len(), b.len());
        assert_eq!(a.positions(), b.positions());
        for i in 0..a.len() {
            for k in 0..3 {
                let (sa, sb) = (a.scales()[i][k], b.scales()[i][k]);
                assert!(
                    (sa - sb).abs() <= 2e-6 * sa.abs() + 1e-30,
                    "scale {i}.{k}: {sa} vs {sb}"
                );
                assert!((a.colors()[i][k] - b.colors()[i][k]).abs() <= 1e-6);
            }
            assert!((a.opacities()[i] - b.opacities()[i]).abs() <= 1e-6);
            for k in 0..4 {
                assert!((a.rotations()[i][k] - b.rotations()[i][k]).abs() <= 1e-6);
            }
        }
        assert_eq!(a.features(), b.features());
    }

    #[test]
    fn a_set_round_trips_within_the_stated_tolerances() {
        for features in [false, true] {
            let set = sample(features);
            assert_close(&decode(&encode(&set)).unwrap(), &set);
        }
    }

    #[test]
    fn the_written_header_is_the_3dgs_layout() {
        let bytes = encode(&sample(true));
        let text = String::from_utf8_lossy(&bytes);
        let text = &text[..text.find("end_header").unwrap()];
        let props: Vec<&str> = text
            .lines()
            .filter_map(|l| l.strip_prefix("property float "))
            .collect();
        assert_eq!(
            props,
            [
                "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "feat_0",
                "feat_1", "feat_2", "feat_3"
            ]
        );
        assert!(text.starts_with("ply\nformat binary_little_endian 1.0\n"));
        assert!(text.contains("element vertex 3\n"));
    }

    #[test]
    fn stored_values_are_logit_log_and_sh_dc() {
        let bytes = encode(&sample(false));
        let body = bytes.len() - 3 * 17 * 4;
        let f = |i: usize| {
            f32::from_le_bytes(bytes[body + i * 4..body + i * 4 + 4].try_into().unwrap())
        };
        // Gaussian 0: rgb (0, 0.5, 1), opacity 0.5, scales (0.01, 0.2, 3).
        assert!((f(6) - (-0.5 / SH_C0) as f32).abs() < 1e-6);
        assert_eq!(f(7), 0.0);
        assert_eq!(f(9), 0.0); // logit(0.5)
        assert!((f(10) - 0.01f32.ln()).abs() < 1e-6);
        assert!((f(12) - 3f32.ln()).abs() < 1e-6);
        // Gaussian 1: opacity 1 is clamped to a finite logit.
        assert!((f(17 + 9) - 16.118).abs() < 1e-2);
        // Gaussian 2: a zero scale is clamped to a finite log.
        assert!((f(34 + 10) - (1e-30f64.ln() as f32)).abs() < 1e-4);
    }
}
