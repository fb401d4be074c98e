//! The job event parser ([`c4g_client::job_event_stream`]) on canned `text/event-stream` bodies,
//! cut into chunks at every awkward place: inside a field name, inside the JSON, between a CR and
//! its LF, inside a multi-byte UTF-8 character.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use bytes::Bytes;
use c4g_client::{Error, Job, job_event_stream};
use futures_util::StreamExt;
use futures_util::stream;

/// A job record as the server writes it, with `state`, `progress` and `history` filled in.
fn record(
    state: &str,
    progress: Option<(u32, u32, &str)>,
    attempt: u32,
    history: &[&str],
) -> String {
    let progress = match progress {
        Some((step, steps, stage)) => {
            serde_json::json!({"step": step, "steps": steps, "stage": stage})
        }
        None => serde_json::Value::Null,
    };
    let done = state == "done";
    serde_json::json!({
        "id": "job-0123456789abcdef0123",
        "clip_id": "3f2a",
        "state": state,
        "attempt": attempt,
        "max_attempts": 3,
        "worker": if state == "running" { serde_json::json!("w1") } else { serde_json::Value::Null },
        "progress": progress,
        "error": null,
        "history": history,
        "request": {"steps": 4, "trajectory": {"kind": "orbit", "depth": 2.0, "angle_degrees": 20.0}},
        "result_frames": if done { 21 } else { 0 },
        "seconds": if done { serde_json::json!(12.5) } else { serde_json::Value::Null },
        "created_at": 1_700_000_000u64,
        "updated_at": 1_700_000_042u64,
        "cancel_requested": false,
    })
    .to_string()
}

/// The canned body: keep-alive comments, an event of another type, LF, CRLF and CR line ends, a
/// stage with non-ASCII text, and an event after the terminal one (never read).
fn body() -> Vec<u8> {
    let mut body = String::new();
    body.push_str(&format!(
        "event: job\ndata: {}\n\n",
        record("queued", None, 1, &[])
    ));
    body.push_str(":\n\n");
    body.push_str(&format!(
        "event: job\r\ndata: {}\r\n\r\n",
        record("running", Some((0, 4, "encoding the context")), 1, &[])
    ));
    body.push_str(": keep-alive\r\n\r\nevent: other\ndata: {\"ignored\": true}\n\n");
    body.push_str(&format!(
        "event: job\rdata: {}\r\r",
        record("running", Some((2, 4, "débruitage ✓")), 1, &[])
    ));
    body.push_str(&format!(
        "event:job\ndata:{}\n\n",
        record(
            "queued",
            None,
            2,
            &["attempt 1: worker w1 stopped responding"]
        )
    ));
    body.push_str(&format!(
        "id: 9\nevent: job\ndata: {}\n\n",
        record(
            "done",
            Some((4, 4, "writing frames")),
            2,
            &["attempt 1: worker w1 stopped responding"]
        )
    ));
    body.push_str(&format!(
        "event: job\ndata: {}\n\n",
        record("failed", None, 3, &[])
    ));
    body.into_bytes()
}

/// Parses `chunks` as a body; every item, errors as their messages.
async fn parse(chunks: Vec<Vec<u8>>) -> Vec<Result<Job, String>> {
    let bytes = stream::iter(chunks.into_iter().map(|c| Ok::<_, Error>(Bytes::from(c))));
    job_event_stream(bytes)
        .map(|item| item.map_err(|e| e.to_string()))
        .collect()
        .await
}

fn summary(jobs: &[Result<Job, String>]) -> Vec<String> {
    jobs.iter()
        .map(|job| {
            let job = job.as_ref().unwrap();
            let progress = job
                .progress
                .as_ref()
                .map(|p| format!(" {}/{} {}", p.step, p.steps, p.stage))
                .unwrap_or_default();
            format!("{} #{}{progress}", job.state, job.attempt)
        })
        .collect()
}

const EXPECTED: [&str; 5] = [
    "queued #1",
    "running #1 0/4 encoding the context",
    "running #1 2/4 débruitage ✓",
    "queued #2",
    "done #2 4/4 writing frames",
];

#[tokio::test]
async fn one_chunk_gives_every_job_and_stops_at_the_terminal_state() {
    let jobs = parse(vec![body()]).await;
    assert_eq!(summary(&jobs), EXPECTED);
    let done = jobs.last().unwrap().as_ref().unwrap();
    assert!(done.is_terminal() && done.is_done());
    assert_eq!(done.id, "job-0123456789abcdef0123");
    assert_eq!(done.clip_id, "3f2a");
    assert_eq!(done.result_frames, 21);
    assert_eq!(done.seconds, Some(12.5));
    assert_eq!(done.max_attempts, 3);
    assert_eq!(done.history, ["attempt 1: worker w1 stopped responding"]);
    assert!(
        done.extra.contains_key("request"),
        "unknown fields are kept"
    );
    let running = jobs[1].as_ref().unwrap();
    assert_eq!(running.worker.as_deref(), Some("w1"));
    assert!(!running.is_terminal());
}

#[tokio::test]
async fn every_split_into_two_chunks_gives_the_same_jobs() {
    let body = body();
    for cut in 0..=body.len() {
        let jobs = parse(vec![body[..cut].to_vec(), body[cut..].to_vec()]).await;
        assert_eq!(summary(&jobs), EXPECTED, "cut at byte {cut}");
    }
}

#[tokio::test]
async fn small_and_uneven_chunks_give_the_same_jobs() {
    let body = body();
    for size in 1..=7 {
        let chunks = body.chunks(size).map(<[u8]>::to_vec).collect();
        assert_eq!(summary(&parse(chunks).await), EXPECTED, "chunks of {size}");
    }
    // Growing chunks, with empty ones in between.
    let mut chunks = Vec::new();
    let (mut at, mut size) = (0, 0);
    while at < body.len() {
        let end = (at + size).min(body.len());
        chunks.push(body[at..end].to_vec());
        chunks.push(Vec::new());
        at = end;
        size = (size + 1) % 13;
    }
    assert_eq!(summary(&parse(chunks).await), EXPECTED);
}

#[tokio::test]
async fn a_body_that_ends_before_the_job_does_is_an_error() {
    let body = body();
    let text = String::from_utf8(body.clone()).unwrap();
    let cut = text.find("event: other").unwrap();
    let jobs = parse(vec![body[..cut].to_vec()]).await;
    assert_eq!(jobs.len(), 3);
    assert_eq!(summary(&jobs[..2]), EXPECTED[..2]);
    let error = jobs[2].as_ref().unwrap_err();
    assert!(error.contains("ended before the job did"), "{error}");
    assert!(error.contains("running"), "{error}");

    let items: Vec<_> = job_event_stream(stream::iter([Ok::<_, Error>(Bytes::from(":\n\n"))]))
        .collect()
        .await;
    assert_eq!(items.len(), 1);
    assert!(matches!(&items[0], Err(Error::Interrupted(_))), "{items:?}");
}

#[tokio::test]
async fn a_transport_error_or_a_bad_record_ends_the_stream() {
    let first = format!("event: job\ndata: {}\n\n", record("queued", None, 1, &[]));
    let chunks = vec![
        Ok(Bytes::from(first.clone())),
        Err(Error::InvalidInput("connection reset".into())),
        Ok(Bytes::from(first.clone())),
    ];
    let items: Vec<_> = job_event_stream(stream::iter(chunks)).collect().await;
    assert_eq!(items.len(), 2);
    assert!(items[0].is_ok());
    assert!(matches!(&items[1], Err(Error::InvalidInput(m)) if m == "connection reset"));

    let chunks = vec![Ok::<_, Error>(Bytes::from(format!(
        "event: job\ndata: {{\"state\": 3}}\n\n{first}"
    )))];
    let items: Vec<_> = job_event_stream(stream::iter(chunks)).collect().await;
    assert_eq!(items.len(), 1);
    assert!(matches!(&items[0], Err(Error::Malformed(_))));
}
