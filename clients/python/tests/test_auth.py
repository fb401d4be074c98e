"""A server with an API key: the client sends it (REST and gRPC), and without it every call
raises Unauthorized with the server's message."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Iterator

import pytest

import c4g_client as c4g
from c4g_client import Client
from conftest import start_server

KEY = "s3cret-key"


@pytest.fixture(scope="module")
def locked(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    proc, url = start_server(tmp_path_factory.mktemp("locked"), {"C4G_API_KEY": KEY})
    try:
        yield url
    finally:
        proc.stop()


def test_the_key_opens_rest_and_grpc(locked: str, frames: list[Path]):
    with Client(locked, api_key=KEY) as client:
        clip = client.upload(frames[:3], fps=10)
        assert len(client.decode(clip.id, [0.0, 0.1])) == 2
        if importlib.util.find_spec("grpc"):
            assert len(list(client.grpc_stream(clip.id, step=0.1))) == 3


def test_without_the_key_calls_are_unauthorized(locked: str, monkeypatch):
    monkeypatch.delenv("C4G_API_KEY", raising=False)
    with Client(locked) as client:
        assert client.ready()  # /ready stays open
        with pytest.raises(c4g.Unauthorized) as e:
            client.clips()
        assert (e.value.status, e.value.kind) == (401, "unauthorized")
        if importlib.util.find_spec("grpc"):
            with pytest.raises(c4g.Unauthorized) as e:
                client.grpc_stream("0" * 24)
            assert e.value.grpc_code == "UNAUTHENTICATED"
    with Client(locked, api_key="wrong") as client, pytest.raises(c4g.Unauthorized):
        client.models()
