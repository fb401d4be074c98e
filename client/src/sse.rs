//! A decoder of server-sent events (`text/event-stream`), as the WHATWG HTML standard defines
//! the format: lines end in LF, CRLF or CR; `field: value` lines build an event; a blank line
//! dispatches it; lines starting with `:` are comments (the server's keep-alives).
//!
//! The decoder is push-based and holds partial lines between chunks, so chunk boundaries may fall
//! anywhere: inside a field name, between a CR and its LF, inside a UTF-8 sequence.

/// One dispatched event.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SseEvent {
    /// The event type (`event:`), `message` when the event named none.
    pub event: String,
    /// The data lines (`data:`), joined with `\n`.
    pub data: String,
    /// The last event id (`id:`) seen on the stream, when there was one.
    pub id: Option<String>,
}

/// Turns the bytes of an event stream into events. See the module documentation.
#[derive(Debug, Clone, Default)]
pub struct SseDecoder {
    /// The current line, not yet terminated.
    line: Vec<u8>,
    /// The previous line ended in CR: an LF that comes next belongs to it.
    after_cr: bool,
    /// A line has been completed (the byte-order mark is only skipped on the first).
    started: bool,
    /// The pending event's type.
    event: String,
    /// The pending event's data, each line followed by `\n`.
    data: String,
    /// The last event id.
    id: Option<String>,
}

impl SseDecoder {
    /// A decoder at the start of a stream.
    pub fn new() -> Self {
        Self::default()
    }

    /// Feeds a chunk of the stream; returns the events it completed, in order.
    pub fn push(&mut self, chunk: &[u8]) -> Vec<SseEvent> {
        let mut events = Vec::new();
        let mut rest = chunk;
        if self.after_cr && !rest.is_empty() {
            self.after_cr = false;
            if rest[0] == b'\n' {
                rest = &rest[1..];
            }
        }
        while let Some(end) = rest.iter().position(|&b| b == b'\n' || b == b'\r') {
            self.line.extend_from_slice(&rest[..end]);
            let cr = rest[end] == b'\r';
            rest = &rest[end + 1..];
            if cr {
                match rest.first() {
                    Some(b'\n') => rest = &rest[1..],
                    Some(_) => {}
                    None => self.after_cr = true,
                }
            }
            if let Some(event) = self.end_line() {
                events.push(event);
            }
        }
        self.line.extend_from_slice(rest);
        events
    }

    /// Handles a completed line; returns an event when the line was blank and one was pending.
    fn end_line(&mut self) -> Option<SseEvent> {
        let mut bytes = std::mem::take(&mut self.line);
        if !self.started {
            self.started = true;
            if bytes.starts_with(b"\xEF\xBB\xBF") {
                bytes.drain(..3);
            }
        }
        if bytes.is_empty() {
            return self.dispatch();
        }
        let line = String::from_utf8_lossy(&bytes);
        if line.starts_with(':') {
            return None;
        }
        let (field, value) = match line.split_once(':') {
            Some((field, value)) => (field, value.strip_prefix(' ').unwrap_or(value)),
            None => (line.as_ref(), ""),
        };
        match field {
            "event" => value.clone_into(&mut self.event),
            "data" => {
                self.data.push_str(value);
                self.data.push('\n');
            }
            "id" if !value.contains('\0') => self.id = Some(value.to_owned()),
            // `retry` and unknown fields are ignored.
            _ => {}
        }
        None
    }

    /// Ends the pending event: no event when it had no data (the standard's rule).
    fn dispatch(&mut self) -> Option<SseEvent> {
        let event = std::mem::take(&mut self.event);
        if self.data.is_empty() {
            return None;
        }
        let mut data = std::mem::take(&mut self.data);
        data.pop();
        Some(SseEvent {
            event: if event.is_empty() {
                "message".to_owned()
            } else {
                event
            },
            data,
            id: self.id.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(chunks: &[&[u8]]) -> Vec<SseEvent> {
        let mut decoder = SseDecoder::new();
        chunks.iter().flat_map(|c| decoder.push(c)).collect()
    }

    #[test]
    fn fields_comments_and_dispatch() {
        let events = decode(&[
            b"\xEF\xBB\xBF: keep-alive\nevent: job\ndata: {\"a\":\ndata:1}\nid: 7\nretry: 10\n\n",
            b"data\n\nevent: empty\n\n",
        ]);
        assert_eq!(
            events,
            vec![
                SseEvent {
                    event: "job".into(),
                    data: "{\"a\":\n1}".into(),
                    id: Some("7".into()),
                },
                SseEvent {
                    event: "message".into(),
                    data: String::new(),
                    id: Some("7".into()),
                },
            ]
        );
    }

    #[test]
    fn cr_lf_split_across_chunks_is_one_line_end() {
        let events = decode(&[b"data: a\r", b"\n\r", b"\ndata: b\r\r"]);
        let data: Vec<_> = events.iter().map(|e| e.data.as_str()).collect();
        assert_eq!(data, ["a", "b"]);
    }

    #[test]
    fn an_unterminated_event_is_not_dispatched() {
        assert!(decode(&[b"data: x\n"]).is_empty());
        assert!(decode(&[b"data: x"]).is_empty());
    }
}
