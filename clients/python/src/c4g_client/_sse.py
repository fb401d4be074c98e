"""Server-sent events (``text/event-stream``), decoded chunk by chunk: how a job's progress
arrives (``GET /v1/jobs/{id}/events``).

The format as the WHATWG HTML standard defines it: lines end in LF, CRLF or CR; ``field: value``
lines build an event; a blank line dispatches it; lines starting with ``:`` are comments (the
server's keep-alives). The decoder holds partial lines between chunks, so a chunk may end
anywhere: inside a field name, between a CR and its LF, inside a UTF-8 sequence.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional


@dataclass(frozen=True)
class SseEvent:
    """One dispatched event: its type (``message`` when it named none), data and last id."""

    event: str
    data: str
    id: Optional[str] = None


class SseDecoder:
    """Turns the bytes of an event stream into :class:`SseEvent` values."""

    def __init__(self) -> None:
        self._line = bytearray()
        self._after_cr = False
        self._started = False
        self._event = ""
        self._data: List[str] = []
        self._id: Optional[str] = None

    def push(self, chunk: bytes) -> List[SseEvent]:
        """Feeds a chunk; returns the events it completed, in order."""
        events: List[SseEvent] = []
        rest = chunk
        if self._after_cr and rest:
            self._after_cr = False
            if rest[:1] == b"\n":
                rest = rest[1:]
        while rest:
            lf, cr = rest.find(b"\n"), rest.find(b"\r")
            ends = [i for i in (lf, cr) if i >= 0]
            if not ends:
                break
            end = min(ends)
            self._line += rest[:end]
            is_cr = rest[end : end + 1] == b"\r"
            rest = rest[end + 1 :]
            if is_cr:
                if rest[:1] == b"\n":
                    rest = rest[1:]
                elif not rest:
                    self._after_cr = True
            event = self._end_line()
            if event is not None:
                events.append(event)
        self._line += rest
        return events

    def _end_line(self) -> Optional[SseEvent]:
        raw = bytes(self._line)
        self._line.clear()
        if not self._started:
            self._started = True
            if raw.startswith(b"\xef\xbb\xbf"):
                raw = raw[3:]
        if not raw:
            return self._dispatch()
        line = raw.decode("utf-8", errors="replace")
        if line.startswith(":"):
            return None
        name, _, value = line.partition(":")
        if value.startswith(" "):
            value = value[1:]
        if name == "event":
            self._event = value
        elif name == "data":
            self._data.append(value)
        elif name == "id" and "\0" not in value:
            self._id = value
        return None

    def _dispatch(self) -> Optional[SseEvent]:
        if not self._data:
            self._event = ""
            return None
        event = SseEvent(self._event or "message", "\n".join(self._data), self._id)
        self._event = ""
        self._data = []
        return event
