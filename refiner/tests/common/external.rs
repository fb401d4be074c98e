//! Moving initializers of an ONNX model into external data, as `onnx.save(...,
//! save_as_external_data=True)` does for models over 2 GiB: the test fixture is small enough to
//! keep its weights inline, the real model is not, and both layouts must merge a LoRA the same.
//!
//! Works on the protobuf wire format directly, copying every field it does not touch byte for
//! byte, so nothing of the model is lost in the rewrite.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeSet;
use std::path::Path;

fn read_varint(buf: &[u8], pos: &mut usize) -> u64 {
    let mut value = 0u64;
    for shift in (0..64).step_by(7) {
        let byte = buf[*pos];
        *pos += 1;
        value |= u64::from(byte & 0x7f) << shift;
        if byte & 0x80 == 0 {
            break;
        }
    }
    value
}

fn write_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// One field of a message: its number, its bytes (key included) and, for length-delimited
/// fields, where the payload is.
struct Field {
    number: u64,
    bytes: std::ops::Range<usize>,
    payload: Option<std::ops::Range<usize>>,
}

fn fields(buf: &[u8]) -> Vec<Field> {
    let mut out = Vec::new();
    let mut pos = 0;
    while pos < buf.len() {
        let start = pos;
        let key = read_varint(buf, &mut pos);
        let payload = match key & 7 {
            0 => {
                read_varint(buf, &mut pos);
                None
            }
            1 => {
                pos += 8;
                None
            }
            5 => {
                pos += 4;
                None
            }
            2 => {
                let len = read_varint(buf, &mut pos) as usize;
                pos += len;
                Some(pos - len..pos)
            }
            other => panic!("wire type {other} in an ONNX model"),
        };
        out.push(Field {
            number: key >> 3,
            bytes: start..pos,
            payload,
        });
    }
    out
}

fn length_delimited(out: &mut Vec<u8>, number: u64, payload: &[u8]) {
    write_varint(out, number << 3 | 2);
    write_varint(out, payload.len() as u64);
    out.extend_from_slice(payload);
}

fn entry(key: &str, value: &str) -> Vec<u8> {
    let mut e = Vec::new();
    length_delimited(&mut e, 1, key.as_bytes());
    length_delimited(&mut e, 2, value.as_bytes());
    e
}

/// Writes `src` to `dst_dir/<file name>` with every initializer `move_it` selects (by name and
/// element count) stored in `<file name>.data` instead. Returns the names moved.
pub fn externalize(
    src: &Path,
    dst_dir: &Path,
    move_it: &dyn Fn(&str, usize) -> bool,
) -> BTreeSet<String> {
    let file_name = src.file_name().unwrap().to_str().unwrap().to_owned();
    let data_name = format!("{file_name}.data");
    let model = std::fs::read(src).unwrap();
    let mut data = Vec::new();
    let mut moved = BTreeSet::new();
    let mut out = Vec::new();
    for f in fields(&model) {
        match (f.number, &f.payload) {
            (7, Some(graph)) => {
                let graph = rewrite_graph(
                    &model[graph.clone()],
                    &data_name,
                    &mut data,
                    &mut moved,
                    move_it,
                );
                length_delimited(&mut out, 7, &graph);
            }
            _ => out.extend_from_slice(&model[f.bytes]),
        }
    }
    std::fs::write(dst_dir.join(&file_name), out).unwrap();
    std::fs::write(dst_dir.join(&data_name), data).unwrap();
    moved
}

fn rewrite_graph(
    graph: &[u8],
    data_name: &str,
    data: &mut Vec<u8>,
    moved: &mut BTreeSet<String>,
    move_it: &dyn Fn(&str, usize) -> bool,
) -> Vec<u8> {
    let mut out = Vec::new();
    for f in fields(graph) {
        let Some(payload) = f.payload.clone().filter(|_| f.number == 5) else {
            out.extend_from_slice(&graph[f.bytes]);
            continue;
        };
        let tensor = &graph[payload];
        let parts = fields(tensor);
        let text = |n: u64| {
            parts
                .iter()
                .find(|p| p.number == n)
                .and_then(|p| p.payload.clone())
                .map(|r| &tensor[r])
        };
        let name = std::str::from_utf8(text(8).unwrap_or_default())
            .unwrap()
            .to_owned();
        let raw = text(9).unwrap_or_default();
        if raw.is_empty() || !move_it(&name, raw.len() / 4) {
            out.extend_from_slice(&graph[f.bytes]);
            continue;
        }
        // Page-aligned, as onnx's external-data writer can do and memory mapping likes.
        data.resize(data.len().next_multiple_of(4096), 0);
        let offset = data.len();
        data.extend_from_slice(raw);
        let mut t = Vec::new();
        for p in &parts {
            if p.number != 9 {
                t.extend_from_slice(&tensor[p.bytes.clone()]);
            }
        }
        for (k, v) in [
            ("location", data_name.to_owned()),
            ("offset", offset.to_string()),
            ("length", raw.len().to_string()),
        ] {
            length_delimited(&mut t, 13, &entry(k, &v));
        }
        write_varint(&mut t, 14 << 3);
        write_varint(&mut t, 1);
        length_delimited(&mut out, 5, &t);
        moved.insert(name);
    }
    out
}
