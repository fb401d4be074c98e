//! A graph's runs and their checked outputs, on the smallest graph there is: `y = Identity(x)`,
//! written here as ONNX protobuf bytes (no model file, no Python).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;

use c4g_runtime::{ErrorKind, Graph, RuntimeError, SessionOptions, session_builder};
use ort::value::TensorRef;

/// Why these tests cannot run here, if they cannot: outside CI a missing ONNX Runtime skips them
/// with a message; in CI (`CI` set) it fails them, so a misconfigured CI cannot pass by running
/// nothing.
fn skip_reason() -> Option<&'static str> {
    if std::env::var_os("ORT_DYLIB_PATH").is_some_and(|p| !p.is_empty()) {
        return None;
    }
    let reason =
        "ORT_DYLIB_PATH is not set (point it at libonnxruntime.so from the onnxruntime wheel)";
    assert!(
        std::env::var_os("CI").is_none(),
        "in CI every runtime test must run: {reason}"
    );
    eprintln!("skipped: {reason}");
    Some(reason)
}

/// The identity graph as a session, named "identity".
fn identity() -> Graph {
    let session = session_builder(Path::new("identity.onnx"), &SessionOptions::default())
        .unwrap()
        .commit_from_memory(&identity_model())
        .unwrap();
    Graph::new("identity", session)
}

/// Runs `graph` on a `[2, 3]` input and reads its output `name` as `expected`.
fn run(graph: &Graph, name: &str, expected: &[usize]) -> Result<Vec<f32>, RuntimeError> {
    let x = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0];
    let input = TensorRef::from_array_view(([2usize, 3], &x[..])).unwrap();
    graph.run(ort::inputs!["x" => input], |outputs| {
        Ok(outputs.f32(name, expected)?.to_vec())
    })
}

#[test]
fn a_run_returns_the_named_output_of_the_expected_shape() {
    if skip_reason().is_some() {
        return;
    }
    let graph = identity();
    assert_eq!(
        run(&graph, "y", &[2, 3]).unwrap(),
        [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    );
}

#[test]
fn a_missing_output_is_a_model_output_error_naming_the_graph_and_the_output() {
    if skip_reason().is_some() {
        return;
    }
    let err = run(&identity(), "z", &[2, 3]).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::ModelOutput);
    assert_eq!(
        err.to_string(),
        "the model produced invalid output: the identity returned no \"z\""
    );
}

#[test]
fn a_wrong_rank_or_dimension_is_a_model_output_error_with_both_shapes() {
    if skip_reason().is_some() {
        return;
    }
    let graph = identity();
    for expected in [&[2, 3, 1][..], &[3, 2], &[2, 4]] {
        let err = run(&graph, "y", expected).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::ModelOutput);
        assert_eq!(
            err.to_string(),
            format!(
                "the model produced invalid output: the identity's \"y\" has shape [2, 3], expected {expected:?}"
            )
        );
    }
}

#[test]
fn a_failed_run_names_the_graph() {
    if skip_reason().is_some() {
        return;
    }
    let graph = identity();
    let x = [0.0f32; 6];
    let input = TensorRef::from_array_view(([2usize, 3], &x[..])).unwrap();
    let err = graph
        .run(ort::inputs!["w" => input], |outputs| {
            Ok(outputs.f32("y", &[2, 3])?.len())
        })
        .unwrap_err();
    assert!(matches!(err, RuntimeError::Ort { .. }), "{err}");
    assert!(
        err.to_string()
            .starts_with("ONNX Runtime failed while running the identity: "),
        "{err}"
    );
    assert_eq!(err.kind(), ErrorKind::Runtime);
}

#[test]
fn a_panic_during_a_run_leaves_the_graph_usable() {
    if skip_reason().is_some() {
        return;
    }
    let graph = identity();
    let x = [0.0f32; 6];
    let panicked = catch_unwind(AssertUnwindSafe(|| {
        let input = TensorRef::from_array_view(([2usize, 3], &x[..])).unwrap();
        graph.run(
            ort::inputs!["x" => input],
            |_| -> Result<(), RuntimeError> {
                panic!("a reader that panics while the lock is held")
            },
        )
    }));
    assert!(panicked.is_err());
    assert_eq!(run(&graph, "y", &[2, 3]).unwrap().len(), 6);
}

#[test]
fn graphs_can_be_shared_between_threads() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<Graph>();
}

/// `y = Identity(x)` for a float tensor `x` of shape `[n, 3]`: ONNX IR 8, opset 13.
fn identity_model() -> Vec<u8> {
    // The protobuf field numbers of onnx.proto.
    let value_info = |name: &str| {
        let dims = [message(2, b"n"), int(1, 3)]
            .map(|d| message(1, &d))
            .concat();
        let tensor_type = [int(1, 1), message(2, &dims)].concat(); // elem_type 1: FLOAT
        let type_proto = message(1, &tensor_type);
        [message(1, name.as_bytes()), message(2, &type_proto)].concat()
    };
    let node = [message(1, b"x"), message(2, b"y"), message(4, b"Identity")].concat();
    let graph = [
        message(1, &node),
        message(2, b"identity"),
        message(11, &value_info("x")),
        message(12, &value_info("y")),
    ]
    .concat();
    let opset = [message(1, b""), int(2, 13)].concat();
    [int(1, 8), message(7, &graph), message(8, &opset)].concat()
}

/// A length-delimited field: a string, bytes or an embedded message.
fn message(field: u64, bytes: &[u8]) -> Vec<u8> {
    let mut out = varint(field << 3 | 2);
    out.extend(varint(bytes.len() as u64));
    out.extend_from_slice(bytes);
    out
}

/// A varint field.
fn int(field: u64, value: u64) -> Vec<u8> {
    [varint(field << 3), varint(value)].concat()
}

fn varint(mut value: u64) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let byte = (value & 0x7f) as u8;
        value >>= 7;
        if value == 0 {
            out.push(byte);
            return out;
        }
        out.push(byte | 0x80);
    }
}
