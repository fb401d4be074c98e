"""Answers read as they arrive: the compact 4D stream's chunked body as an iterator of sets
(:class:`SetStream`, :class:`AsyncSetStream`) and a job's server-sent events as an iterator of
job records (:func:`job_events`, :func:`ajob_events`).

Both hold an open response; exhausting the iterator, ``close()`` or a ``with`` block releases
it, and closing early stops the server's work at its next set (it sees the connection go). A
body that ends before its last record (the C4GV index, a terminal job state) raises
:class:`~c4g_client.StreamInterrupted`: the server hit an error after the first byte, or the
connection dropped, and a caller may ask again.
"""

from __future__ import annotations

from typing import Any, AsyncIterator, Callable, Iterator, List, Optional

import httpx

from ._approx import SCENE_HEADER
from ._c4gv import C4GVDecoder, Header, IndexEntry
from ._endpoints import job_from_event, sets_header
from ._errors import StreamInterrupted
from ._records import Job
from ._sets import GaussianSet
from ._sse import SseDecoder

JobCallback = Callable[[Job], Any]


class _Sets:
    """What both stream classes share: the decoder and what the response's headers said."""

    def __init__(self, response: httpx.Response) -> None:
        self._response = response
        self._decoder = C4GVDecoder()
        self._pending: List[GaussianSet] = []
        #: How many sets the server said follow (``X-C4G-Sets``).
        self.expected: Optional[int] = sets_header(response)
        #: The scene that serves the stream (``X-C4G-Scene``: ``feed-forward`` or ``fitted``).
        self.scene: Optional[str] = response.headers.get(SCENE_HEADER)

    @property
    def header(self) -> Optional[Header]:
        """The stream's header (N, static mask, grid steps) once it has arrived."""
        return self._decoder.header

    @property
    def index(self) -> Optional[List[IndexEntry]]:
        """The index record (time, offset, keyframe of every set) once the stream is whole."""
        return self._decoder.index

    @property
    def position_error(self) -> Optional[float]:
        """The stream's stated bound on each position coordinate, scene units."""
        header = self._decoder.header
        return header.position_error if header else None

    def _push(self, chunk: bytes) -> None:
        self._decoder.feed(chunk)
        self._pending.extend(self._decoder.frames())


class SetStream(_Sets):
    """The sets of ``POST /v1/clips/{id}/stream``, decoded as the bytes arrive."""

    def __init__(self, response: httpx.Response) -> None:
        super().__init__(response)
        self._chunks = response.iter_bytes()

    def __iter__(self) -> Iterator[GaussianSet]:
        return self

    def __next__(self) -> GaussianSet:
        while not self._pending:
            try:
                chunk = next(self._chunks)
            except StopIteration:
                self.close()
                self._decoder.finish()
                raise
            except httpx.HTTPError as e:
                self.close()
                raise StreamInterrupted(f"the stream's connection failed: {e}") from e
            try:
                self._push(chunk)
            except BaseException:
                self.close()
                raise
        return self._pending.pop(0)

    def close(self) -> None:
        self._response.close()

    def __enter__(self) -> SetStream:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class AsyncSetStream(_Sets):
    """:class:`SetStream` for an :class:`~c4g_client.AsyncClient`: ``async for``."""

    def __init__(self, response: httpx.Response) -> None:
        super().__init__(response)
        self._chunks = response.aiter_bytes()

    def __aiter__(self) -> AsyncIterator[GaussianSet]:
        return self

    async def __anext__(self) -> GaussianSet:
        while not self._pending:
            try:
                chunk = await self._chunks.__anext__()
            except StopAsyncIteration:
                await self.aclose()
                self._decoder.finish()
                raise
            except httpx.HTTPError as e:
                await self.aclose()
                raise StreamInterrupted(f"the stream's connection failed: {e}") from e
            try:
                self._push(chunk)
            except BaseException:
                await self.aclose()
                raise
        return self._pending.pop(0)

    async def aclose(self) -> None:
        await self._response.aclose()

    async def __aenter__(self) -> AsyncSetStream:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()


def _jobs_in(decoder: SseDecoder, chunk: bytes) -> List[Job]:
    """The job records of the ``job`` events a chunk completes (comments, other events
    skipped)."""
    return [job_from_event(e.data) for e in decoder.push(chunk) if e.event == "job"]


_CUT = "the job's event stream ended before the job did"


def job_events(response: httpx.Response, progress: Optional[JobCallback]) -> Iterator[Job]:
    """A job's records as they change, ending after its first terminal state."""
    decoder = SseDecoder()
    try:
        for chunk in response.iter_bytes():
            for job in _jobs_in(decoder, chunk):
                if progress:
                    progress(job)
                yield job
                if job.is_terminal:
                    return
    except httpx.HTTPError as e:
        raise StreamInterrupted(f"{_CUT}: {e}") from e
    finally:
        response.close()
    raise StreamInterrupted(_CUT)


async def ajob_events(response: httpx.Response, progress: Optional[JobCallback]) -> AsyncIterator[Job]:
    """:func:`job_events` for an async client."""
    decoder = SseDecoder()
    try:
        async for chunk in response.aiter_bytes():
            for job in _jobs_in(decoder, chunk):
                if progress:
                    progress(job)
                yield job
                if job.is_terminal:
                    return
    except httpx.HTTPError as e:
        raise StreamInterrupted(f"{_CUT}: {e}") from e
    finally:
        await response.aclose()
    raise StreamInterrupted(_CUT)
