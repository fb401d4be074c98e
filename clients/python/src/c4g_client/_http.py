"""The REST plumbing both clients share: where the server is, how to authenticate, what a
request is before it is sent (:class:`Call`), and how an error answer becomes an exception.

Every operation is described once, as a :class:`Call` (method, path, body, and the function
that reads its answer), in ``_endpoints.py``; :class:`~c4g_client.Client` sends calls with a
blocking ``httpx.Client`` and :class:`~c4g_client.AsyncClient` with an ``httpx.AsyncClient``.
So the two cannot drift apart: they differ only in how they wait.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Generic, Mapping, Optional, Sequence, TypeVar
from urllib.parse import quote, urlsplit

import httpx

from ._errors import ApiError, FormatError, api_error, kind_for_status

T = TypeVar("T")

#: Connecting may take 10 s; the answer has no deadline: an upload waits for its encode, and a
#: long video renders for as long as it takes.
DEFAULT_TIMEOUT = httpx.Timeout(None, connect=10.0)

USER_AGENT = "c4g-client-python/0.1.0"


@dataclass
class Call(Generic[T]):
    """One REST request, not yet sent, and the function that reads its (successful) answer."""

    method: str
    path: Sequence[str]
    parse: Callable[[httpx.Response], T]
    json: Any = None
    params: Optional[Mapping[str, str]] = None
    headers: Dict[str, str] = field(default_factory=dict)
    #: A body other than JSON: bytes, or an (async) iterator of chunks (an upload).
    content: Any = None

    def request(self, http: Any, base_url: str) -> httpx.Request:
        """The request on ``http`` (an ``httpx.Client`` or ``AsyncClient``)."""
        content = self.content
        headers = dict(self.headers)
        if self.json is not None:
            content = json.dumps(self.json, allow_nan=False).encode()
            headers.setdefault("content-type", "application/json")
        request: httpx.Request = http.build_request(
            self.method,
            url_for(base_url, self.path),
            content=content,
            params=self.params,
            headers=headers,
        )
        return request


def normalise_base_url(url: str) -> str:
    """``http://host:port[/prefix]`` without a trailing slash; a bare ``host:port`` means
    ``http://host:port``."""
    if "://" not in url:
        url = "http://" + url
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https"):
        raise ValueError(f"unsupported scheme {parts.scheme!r} in {url!r}; use http:// or https://")
    if not parts.hostname:
        raise ValueError(f"no host in {url!r}")
    return url.rstrip("/")


def url_for(base_url: str, segments: Sequence[str]) -> str:
    """The URL of ``segments`` under the base URL, each percent-encoded: ids are the server's,
    but nothing stops a caller from passing any string, and ``a/b`` must stay one segment."""
    return base_url + "/" + "/".join(quote(str(s), safe="") for s in segments)


def auth_headers(api_key: Optional[str]) -> Dict[str, str]:
    """Headers every request carries: the user agent, and the API key as a bearer token."""
    headers = {"user-agent": USER_AGENT}
    if api_key:
        headers["authorization"] = f"Bearer {api_key}"
    return headers


def error_from(response: httpx.Response) -> ApiError:
    """The exception for an error answer whose body has been read: the API's JSON
    ``{"error", "kind"}`` when it is that, else the status's kind and the body's text (a
    proxy's page, an empty body)."""
    retry_after: Optional[float] = None
    try:
        retry_after = float(response.headers.get("retry-after", ""))
    except ValueError:
        pass
    kind, message = "", ""
    try:
        body = response.json()
        if isinstance(body, dict) and isinstance(body.get("kind"), str):
            kind, message = body["kind"], str(body.get("error", ""))
    except ValueError:
        pass
    if not kind:
        kind = kind_for_status(response.status_code)
        text = response.text.strip()
        message = text[:500] if text else response.reason_phrase
    return api_error(response.status_code, kind, message, retry_after=retry_after)


def read_json(response: httpx.Response) -> Any:
    """The answer's JSON; a body of another shape is a :class:`FormatError`, not a crash."""
    try:
        return response.json()
    except ValueError as e:
        raise FormatError(f"the server's answer is not JSON ({e})") from None
