//! What a REST request carries, read with the service's errors: JSON bodies, path segments and
//! query strings. Every refusal is the JSON error of `error.rs`, never axum's plain-text one.
//!
//! JSON bodies are held to the rules `openapi.json` states for every one of them: an object
//! (no body at all reads as `{}`), no `null` (leave a field out to get its default), nesting at
//! most [`MAX_DEPTH`] deep, and at most [`MAX_JSON_BYTES`] bytes. JSON does not tell `5.0` from
//! `5`, so neither does the service: a whole number written with a fraction reads as an
//! integer. A malformed body (including `NaN`, which JSON does not have) is a 400 with serde's
//! description of where it went wrong.
//!
//! Decode, render and refinement bodies are held here to the ranges `openapi.json` states for
//! the numbers the service reads as 32-bit floats ([`check_body`]): cameras and trajectory
//! presets (the core checks what they mean; these bounds keep every product the renderer forms
//! finite), pruning floors, backgrounds and embeddings.

use axum::extract::rejection::BytesRejection;
use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::StatusCode;
use axum::http::request::Parts;
use bytes::Bytes;
use serde::de::DeserializeOwned;
use serde_json::Value;

use c4g_service::ServiceError;
use c4g_service::clips::intake::cameras::{FOCAL_BOUND, SMALLEST_LENGTH};
use c4g_service::quoted;
use c4g_service::views::camera::{SCENE_BOUND, check_preset, within};

use crate::error::ErrorReply;

/// Largest JSON request body, bytes (a longer one is a 413).
pub const MAX_JSON_BYTES: usize = 2 << 20;

/// Deepest nesting of arrays and objects in a JSON body (the deepest the API uses is 5).
pub const MAX_DEPTH: usize = 16;

/// A JSON body; no body (zero bytes) reads as `{}`.
pub struct JsonBody<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned> FromRequest<S> for JsonBody<T> {
    type Rejection = ErrorReply;

    async fn from_request(request: Request, state: &S) -> Result<Self, Self::Rejection> {
        let bytes = Bytes::from_request(request, state)
            .await
            .map_err(body_error)?;
        Ok(parse(&bytes).map(JsonBody)?)
    }
}

fn body_error(rejection: BytesRejection) -> ServiceError {
    if rejection.status() == StatusCode::PAYLOAD_TOO_LARGE {
        ServiceError::TooLarge(format!(
            "the JSON body is over {MAX_JSON_BYTES} bytes: send large inputs over gRPC"
        ))
    } else {
        ServiceError::invalid(format!("cannot read the request body: {rejection}"))
    }
}

/// A JSON body as `T`, held to the rules in the module doc.
pub fn parse<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, ServiceError> {
    // No body at all is no options; anything else must be JSON (whitespace alone is not).
    let text: &[u8] = if bytes.is_empty() { b"{}" } else { bytes };
    let mut value: Value = serde_json::from_slice(text)
        .map_err(|e| ServiceError::invalid(format!("the JSON body is not valid: {e}")))?;
    if !value.is_object() {
        return Err(ServiceError::invalid(
            "the JSON body must be an object ({...})",
        ));
    }
    check(&mut value, 0).map_err(Refusal::into_error)?;
    typed(value)
}

/// A checked JSON value (from [`JsonBody<Value>`]) as `T`.
pub fn typed<T: DeserializeOwned>(value: Value) -> Result<T, ServiceError> {
    serde_json::from_value(value)
        .map_err(|e| ServiceError::invalid(format!("the JSON body is not valid: {e}")))
}

/// What [`check`] refused, and where: the path is collected on the way out, innermost first, so
/// that nothing is built for a body that passes.
struct Refusal {
    null: bool,
    path: Vec<String>,
}

impl Refusal {
    fn at(mut self, segment: String) -> Self {
        self.path.push(segment);
        self
    }

    fn into_error(self) -> ServiceError {
        let pointer: String = self.path.iter().rev().map(|s| format!("/{s}")).collect();
        let pointer = if pointer.is_empty() {
            "/".into()
        } else {
            pointer
        };
        ServiceError::invalid(if self.null {
            format!("the JSON body has null at {pointer}: leave a field out to get its default")
        } else {
            format!("the JSON body nests deeper than {MAX_DEPTH} levels at {pointer}")
        })
    }
}

/// Refuses `null` and nesting past [`MAX_DEPTH`], and writes whole numbers as integers.
fn check(value: &mut Value, depth: usize) -> Result<(), Refusal> {
    let refuse = |null| {
        Err(Refusal {
            null,
            path: Vec::new(),
        })
    };
    match value {
        Value::Null => refuse(true),
        Value::Number(n) => {
            if let Some(whole) = whole_number(n) {
                *value = whole;
            }
            Ok(())
        }
        Value::Array(_) | Value::Object(_) if depth >= MAX_DEPTH => refuse(false),
        Value::Array(items) => items
            .iter_mut()
            .enumerate()
            .try_for_each(|(i, v)| check(v, depth + 1).map_err(|r| r.at(i.to_string()))),
        Value::Object(fields) => fields.iter_mut().try_for_each(|(k, v)| {
            check(v, depth + 1).map_err(|r| r.at(k.replace('~', "~0").replace('/', "~1")))
        }),
        Value::Bool(_) | Value::String(_) => Ok(()),
    }
}

/// A float with no fraction, within the integers serde reads, as that integer (`5.0` → `5`).
///
/// Exact: serde_json reads with its `float_roundtrip` feature (the workspace's `Cargo.toml`), so a
/// float arrives as the nearest f64 to what was written and only one with no fraction at all is
/// whole. A float within an ulp of a whole number is still a float (`-999999.9999999999` is not
/// `-1000000`, which a bound of "above -1e6" refuses).
fn whole_number(n: &serde_json::Number) -> Option<Value> {
    let v = n.as_f64().filter(|_| n.is_f64())?;
    if v.fract() != 0.0 {
        return None;
    }
    // Exact: both bounds are powers of two, and every float between them with no fraction is an
    // integer of the type.
    if (0.0..18_446_744_073_709_551_616.0).contains(&v) {
        Some(Value::from(v as u64))
    } else if (-9_223_372_036_854_775_808.0..0.0).contains(&v) {
        Some(Value::from(v as i64))
    } else {
        None
    }
}

/// Largest magnitude of a number the service keeps as a 32-bit float: under `f32::MAX`, and
/// written with few digits, so that every JSON reader reads the bound itself exactly.
pub const FLOAT_BOUND: f64 = 1e38;

/// Holds a decode, render or refinement body to what `openapi.json` states beyond the types of
/// its fields: the range of every number the service reads as a 32-bit float (checked here, on
/// the number as sent: once rounded to 32 bits, `1.0000000000000002` would pass for `1`), a
/// camera matrix's last row, a trajectory preset's own fields, and one to `max_times` cameras.
/// Values of the wrong type are left to serde, which names them.
pub fn check_body(body: &Value, max_times: usize) -> Result<(), ServiceError> {
    if let Some(camera) = body.get("camera") {
        check_camera(camera, "camera")?;
    }
    if let Some(Value::Array(cameras)) = body.get("cameras") {
        if cameras.is_empty() || cameras.len() > max_times {
            return Err(ServiceError::invalid(format!(
                "cameras lists one camera per frame: 1 to {max_times} (C4G_MAX_TIMES), got {}",
                cameras.len()
            )));
        }
        for (i, camera) in cameras.iter().enumerate() {
            check_camera(camera, &format!("cameras[{i}]"))?;
        }
    }
    if let Some(preset) = body.get("trajectory") {
        check_preset(preset)?;
    }
    if let Some(prune) = body.get("prune") {
        within(prune.get("opacity"), "prune opacity", 0.0, 1.0)?;
        within(
            prune.get("contribution_px"),
            "prune contribution_px",
            0.0,
            FLOAT_BOUND,
        )?;
        // Named here: serde's own message for a wrong type names the type, not the field.
        if let Some(drop) = prune.get("drop_queries")
            && !drop.is_boolean()
        {
            return Err(ServiceError::invalid(format!(
                "prune drop_queries is true or false, got {drop}"
            )));
        }
    }
    for name in [
        "background",
        "text_embedding",
        "negative_embedding",
        "feature",
    ] {
        if let Some(Value::Array(items)) = body.get(name) {
            for (i, v) in items.iter().enumerate() {
                within(Some(v), &format!("{name}[{i}]"), -FLOAT_BOUND, FLOAT_BOUND)?;
            }
        }
    }
    Ok(())
}

fn check_camera(camera: &Value, name: &str) -> Result<(), ServiceError> {
    if let Some(Value::Array(matrix)) = camera.get("world_to_camera") {
        // Checked here too, not only where the camera is used: beside explicit `cameras` a
        // `camera` is not.
        if matrix.len() != 16 {
            return Err(ServiceError::invalid(format!(
                "{name} world_to_camera needs 16 numbers (row-major 4x4), got {}",
                matrix.len()
            )));
        }
        let numbers: Vec<f64> = matrix.iter().filter_map(Value::as_f64).collect();
        if numbers.len() == 16 && numbers[12..] != [0.0, 0.0, 0.0, 1.0] {
            return Err(ServiceError::invalid(format!(
                "{name} world_to_camera must end in the row 0 0 0 1, got {:?}",
                &numbers[12..]
            )));
        }
        for (i, v) in matrix.iter().take(12).enumerate() {
            let entry = format!("{name} world_to_camera[{i}]");
            within(Some(v), &entry, -SCENE_BOUND, SCENE_BOUND)?;
        }
    }
    if let Some(k) = camera.get("intrinsics") {
        let focal = SMALLEST_LENGTH..=FOCAL_BOUND;
        within(
            k.get("fx"),
            &format!("{name} fx"),
            *focal.start(),
            *focal.end(),
        )?;
        within(
            k.get("fy"),
            &format!("{name} fy"),
            *focal.start(),
            *focal.end(),
        )?;
        within(
            k.get("cx"),
            &format!("{name} cx"),
            -FOCAL_BOUND,
            FOCAL_BOUND,
        )?;
        within(
            k.get("cy"),
            &format!("{name} cy"),
            -FOCAL_BOUND,
            FOCAL_BOUND,
        )?;
    }
    Ok(())
}

/// A path segment that names a clip: the 24 lowercase hex digits of its content address.
/// Anything else names no clip (404), whatever it holds.
pub struct ClipId(pub String);

/// A path segment that names a refinement job: `job-` and 20 lowercase hex digits.
pub struct JobId(pub String);

impl<S: Send + Sync> FromRequestParts<S> for ClipId {
    type Rejection = ErrorReply;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        let id = first_segment(parts, state).await?;
        if is_hex(&id, 24) {
            Ok(Self(id))
        } else {
            Err(ServiceError::NotFound(format!(
                "no clip {id_quoted}: clip ids are 24 lowercase hex digits (GET /v1/clips lists them)", id_quoted = quoted(&id)))
            .into())
        }
    }
}

impl<S: Send + Sync> FromRequestParts<S> for JobId {
    type Rejection = ErrorReply;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        let id = first_segment(parts, state).await?;
        if id.strip_prefix("job-").is_some_and(|hex| is_hex(hex, 20)) {
            Ok(Self(id))
        } else {
            Err(ServiceError::NotFound(format!(
                "no job {id_quoted}: job ids are `job-` and 20 lowercase hex digits (GET /v1/jobs \
                 lists them)",
                id_quoted = quoted(&id)
            ))
            .into())
        }
    }
}

fn is_hex(text: &str, len: usize) -> bool {
    text.len() == len && text.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

/// The route's first path parameter (`{id}`), percent-decoded.
async fn first_segment<S: Send + Sync>(
    parts: &mut Parts,
    state: &S,
) -> Result<String, ServiceError> {
    let params = axum::extract::RawPathParams::from_request_parts(parts, state)
        .await
        .map_err(|e| ServiceError::invalid(format!("the path cannot be read: {e}")))?;
    params
        .iter()
        .next()
        .map(|(_, value)| value.to_owned())
        .ok_or_else(|| ServiceError::Internal("the route has no path parameter".into()))
}

/// The route's second path parameter (`{index}`) as a context frame index: anything but a
/// decimal number in range names no frame (404).
pub struct FrameIndex(pub usize);

impl<S: Send + Sync> FromRequestParts<S> for FrameIndex {
    type Rejection = ErrorReply;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, Self::Rejection> {
        let params = axum::extract::RawPathParams::from_request_parts(parts, state)
            .await
            .map_err(|e| ServiceError::invalid(format!("the path cannot be read: {e}")))?;
        let raw = params
            .iter()
            .nth(1)
            .map(|(_, value)| value.to_owned())
            .ok_or_else(|| ServiceError::Internal("the route has no frame index".into()))?;
        decimal(&raw).map(Self).ok_or_else(|| {
            ServiceError::NotFound(format!(
                "no context frame {raw_quoted}: frames are numbered 0, 1, ...",
                raw_quoted = quoted(&raw)
            ))
            .into()
        })
    }
}

/// A non-negative decimal integer written plainly (digits only), within `usize`.
pub fn decimal(text: &str) -> Option<usize> {
    if text.is_empty() || !text.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    text.parse().ok()
}

/// The query string's `name=value` pairs, in order; a malformed query string is a 400.
pub fn query_pairs(query: Option<&str>) -> Result<Vec<(String, String)>, ServiceError> {
    let query = query.unwrap_or("");
    axum::extract::Query::<Vec<(String, String)>>::try_from_uri(
        &format!("/?{query}")
            .parse()
            .map_err(|_| ServiceError::invalid("the query string is malformed"))?,
    )
    .map(|q| q.0)
    .map_err(|e| ServiceError::invalid(format!("the query string is malformed: {e}")))
}

#[cfg(test)]
mod tests {
    use serde::Deserialize;

    use super::*;

    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Body {
        t: Option<f64>,
        times: Option<Vec<f64>>,
        nested: Option<Value>,
    }

    fn refusal(text: &str) -> String {
        match parse::<Body>(text.as_bytes()) {
            Ok(body) => panic!("{text} was accepted as {body:?}"),
            Err(e) => {
                assert_eq!(e.kind(), c4g_service::ServiceErrorKind::InvalidInput);
                e.to_string()
            }
        }
    }

    #[test]
    fn an_empty_body_is_an_empty_object_and_a_good_one_reads() {
        assert!(parse::<Body>(b"").unwrap().t.is_none());
        assert!(refusal("\r").contains("not valid"));
        assert_eq!(parse::<Body>(br#"{"t": 0.5}"#).unwrap().t, Some(0.5));
    }

    #[test]
    fn null_anywhere_is_refused_with_where_it_is() {
        assert!(refusal(r#"{"t": 0, "times": null}"#).contains("null at /times"));
        assert!(refusal(r#"{"nested": {"a/b": [1, null]}}"#).contains("/nested/a~1b/1"));
        assert!(refusal("null").contains("must be an object"));
    }

    #[test]
    fn a_body_that_is_not_an_object_is_refused() {
        // serde reads a struct from an array too: `[0.5]` must not become {"t": 0.5}.
        for text in ["[0.5]", "0.5", "\"t\"", "true"] {
            assert!(refusal(text).contains("must be an object"), "{text}");
        }
    }

    #[test]
    fn nesting_past_the_limit_is_refused_before_serde_sees_it() {
        let ok = format!("{{\"nested\": {}{}}}", "[".repeat(14), "]".repeat(14));
        assert!(parse::<Body>(ok.as_bytes()).is_ok());
        let deep = format!("{{\"nested\": {}{}}}", "[".repeat(16), "]".repeat(16));
        assert!(refusal(&deep).contains("nests deeper than 16"));
        // Far past serde_json's own recursion limit: still a 400, not a stack overflow.
        let abyss = format!(
            "{{\"nested\": {}{}}}",
            "[".repeat(100_000),
            "]".repeat(100_000)
        );
        assert!(refusal(&abyss).contains("not valid"));
    }

    #[test]
    fn whole_numbers_written_with_a_fraction_read_as_integers() {
        #[derive(Deserialize)]
        struct Counts {
            count: usize,
            seed: u64,
            shift: f64,
        }
        let counts: Counts = parse(br#"{"count": 5.0, "seed": 1e19, "shift": 2.0}"#).unwrap();
        assert_eq!(
            (counts.count, counts.seed, counts.shift),
            (5, 10_000_000_000_000_000_000, 2.0)
        );
        assert_eq!(
            parse::<Counts>(br#"{"count": -0.0, "seed": 0, "shift": 0}"#)
                .unwrap()
                .count,
            0
        );
        assert!(parse::<Counts>(br#"{"count": 5.5, "seed": 0, "shift": 0}"#).is_err());
        assert!(parse::<Counts>(br#"{"count": 1e20, "seed": 0, "shift": 0}"#).is_err());
        // A long float is read exactly (float_roundtrip): whole when written whole …
        let long: Counts =
            parse(br#"{"count": 0, "seed": 1990241308034915.0, "shift": 0}"#).unwrap();
        assert_eq!(long.seed, 1_990_241_308_034_915);
        // … and a float an ulp from a whole number stays that float (schemathesis sent a
        // control_scale of -999999.9999999999 against a bound of "above -1e6", which read as
        // -1e6 when floats that close counted as whole).
        let near: Counts =
            parse(br#"{"count": 0, "seed": 0, "shift": -999999.9999999999}"#).unwrap();
        assert!(near.shift > -1e6, "{}", near.shift);
    }

    #[test]
    fn numbers_that_json_cannot_carry_are_refused() {
        assert!(parse::<Body>(br#"{"t": 1e300}"#).is_ok());
        assert!(refusal(r#"{"t": 1e400}"#).contains("not valid"));
        assert!(refusal(r#"{"t": NaN}"#).contains("not valid"));
    }

    fn body_refusal(body: Value) -> String {
        check_body(&body, 8).unwrap_err().to_string()
    }

    #[test]
    fn float32_fields_are_held_to_their_bounds_as_sent_not_as_rounded() {
        let good = serde_json::json!({
            "camera": {"world_to_camera": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, -2, 0, 0, 0, 1],
                       "intrinsics": {"fx": 1e-6, "fy": 1000, "cx": -1000, "cy": 0.5}},
            "cameras": [{}, {"intrinsics": {"fx": 0.8, "fy": 0.8}}],
            "trajectory": {"kind": "spiral", "radii": [0, 1, 1e6], "focus_depth": 1e6,
                           "rotations": -1e6, "z_rate": 0.5},
            "prune": {"opacity": 1, "contribution_px": 1e38},
            "background": [-1e38, 0, 1],
        });
        check_body(&good, 8).unwrap();
        // Each of these is 1.0 or 1e6 once rounded to 32 bits, and outside the schema's bound.
        assert!(
            body_refusal(serde_json::json!({"prune": {"opacity": 1.0000000000000002}}))
                .contains("prune opacity")
        );
        assert!(
            body_refusal(serde_json::json!({"trajectory": {"kind": "spiral",
                "radii": [0, 0, 0], "focus_depth": 1000000.0000000001, "rotations": 1,
                "z_rate": 1}}))
            .contains("spiral focus_depth")
        );
        let row = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0];
        let mut matrix: Vec<Value> = row.iter().map(|&v| v.into()).collect();
        matrix.push(1.0000000000000002.into());
        assert!(
            body_refusal(serde_json::json!({"cameras": [{"world_to_camera": matrix}]}))
                .contains("cameras[0] world_to_camera must end in the row 0 0 0 1")
        );
        assert!(
            body_refusal(serde_json::json!({"camera": {"world_to_camera": [1, 0, 0]}}))
                .contains("camera world_to_camera needs 16 numbers")
        );
        assert!(
            body_refusal(serde_json::json!({"background": [0, 0, 1.0000000000000001e38]}))
                .contains("background[2]")
        );
        assert!(
            body_refusal(serde_json::json!({"camera": {"intrinsics": {"fx": 9.9e-7, "fy": 1}}}))
                .contains("camera fx")
        );
    }

    #[test]
    fn a_preset_takes_its_own_fields_and_cameras_come_one_to_max_times() {
        assert!(
            body_refusal(
                serde_json::json!({"trajectory": {"kind": "dolly", "distance": 1,
                "depth": 2}})
            )
            .contains("unknown field `depth` in the trajectory: a dolly takes distance")
        );
        assert!(body_refusal(serde_json::json!({"cameras": []})).contains("1 to 8"));
        let nine = vec![serde_json::json!({}); 9];
        assert!(body_refusal(serde_json::json!({ "cameras": nine })).contains("got 9"));
        // Kinds and types serde knows better are left to serde.
        check_body(&serde_json::json!({"trajectory": {"kind": "loop"}}), 8).unwrap();
        check_body(&serde_json::json!({"prune": {"opacity": "high"}}), 8).unwrap();
    }

    #[test]
    fn only_plain_decimals_are_indices() {
        assert_eq!(decimal("0"), Some(0));
        assert_eq!(decimal("012"), Some(12));
        for bad in [
            "",
            "-1",
            "+1",
            "1.0",
            "1e3",
            " 1",
            "null",
            "99999999999999999999999",
        ] {
            assert_eq!(decimal(bad), None, "{bad}");
        }
    }

    #[test]
    fn ids_are_hex_of_their_length() {
        assert!(is_hex("0123456789abcdef01234567", 24));
        assert!(!is_hex("0123456789ABCDEF01234567", 24));
        assert!(!is_hex("../../../../etc/passwd00", 24));
        assert!(!is_hex("0123456789abcdef0123456", 24));
    }
}
