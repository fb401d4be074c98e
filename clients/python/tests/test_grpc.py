"""gRPC StreamGaussians through the client (the ``grpc`` extra), and the committed messages
against what ``generate-grpc`` makes from the proto today."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import Client
from conftest import PACKAGE, REPO

pytest.importorskip("grpc")

FIELDS = ("means", "quats", "scales", "opacities", "colors")


def test_grpc_sets_equal_the_rest_decodes(client: Client, clip: c4g.Clip):
    with client.grpc_stream(clip.id, start=0.0, end=0.6, step=0.1) as stream:
        sets = list(stream)
    assert len(sets) == 7
    exact = client.decode(clip.id, [s.time for s in sets])
    for got, want in zip(sets, exact):
        assert got.time == want.time
        for name in FIELDS:
            assert getattr(got, name).tobytes() == getattr(want, name).tobytes(), name


def test_grpc_f16_sets_are_the_rest_f16_decodes(client: Client, clip: c4g.Clip):
    sets = list(client.grpc_stream(clip.id, fps=5, precision="f16"))
    rest = client.decode(clip.id, [s.time for s in sets], precision="f16")
    for got, want in zip(sets, rest):
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_the_grpc_compact_stream_is_the_rest_compact_stream(client: Client, clip: c4g.Clip):
    over_grpc = list(client.grpc_stream(clip.id, step=0.05, compact=1e-3, keyframe_interval=4))
    over_rest = list(client.stream(clip.id, step=0.05, position_error=1e-3, keyframe_interval=4))
    assert [s.time for s in over_grpc] == [s.time for s in over_rest]
    for a, b in zip(over_grpc, over_rest):
        for name in FIELDS:
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes()


def test_grpc_options_pass_through(client: Client, clip: c4g.Clip):
    pruned = list(client.grpc_stream(clip.id, step=0.2, quality="fast", prune=c4g.Prune(contribution_px=0.5)))
    assert len(pruned[0]) < 512
    keyed = list(client.grpc_stream(clip.id, step=0.1, keyframes=c4g.Keyframes.adaptive(0.01, max=8)))
    assert len(keyed) == 7


def test_grpc_errors_carry_the_servers_kind(client: Client, clip: c4g.Clip):
    with pytest.raises(c4g.NotFound) as e:
        client.grpc_stream("0" * 24)
    assert e.value.grpc_code == "NOT_FOUND" and e.value.status == 404 and "no clip" in e.value.message
    with pytest.raises(c4g.InvalidInput) as e:
        client.grpc_stream(clip.id, start=0.0, end=9.0)
    assert e.value.grpc_code == "INVALID_ARGUMENT" and e.value.kind == "invalid_input"
    with pytest.raises(c4g.TransportError):
        Client("http://127.0.0.1:9").grpc_stream(clip.id)


def test_a_clients_grpc_calls_share_one_channel_that_closing_the_client_closes(
    server: str, clip: c4g.Clip, monkeypatch
):
    import grpc

    opened = []
    open_channel = grpc.insecure_channel

    def counted(*args, **kwargs):
        opened.append(open_channel(*args, **kwargs))
        return opened[-1]

    monkeypatch.setattr(grpc, "insecure_channel", counted)
    with Client(server) as c:
        c.decode(clip.id, 0.1)
        assert opened == []  # opened by the first gRPC call, not before
        assert len(list(c.grpc_stream(clip.id, start=0.0, end=0.1, step=0.1))) == 2
        with c.grpc_stream(clip.id, step=0.1) as stopped_early:
            next(stopped_early)
        assert len(c.grpc_decode(clip.id, [0.2, 0.3])) == 2
        assert len(opened) == 1
    # Closed with the client: the channel refuses calls, and so does the client.
    with pytest.raises(ValueError, match="closed channel"):
        opened[0].unary_unary("/c4g.v1.C4G/Decode")(b"")
    with pytest.raises(RuntimeError, match="closed"):
        c.grpc_decode(clip.id, 0.2)
    assert len(opened) == 1


def test_the_committed_grpc_messages_are_what_the_proto_makes(tmp_path: Path):
    pytest.importorskip("grpc_tools")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "grpc_tools.protoc",
            "-I",
            str(REPO / "proto"),
            f"--python_out={tmp_path}",
            f"--pyi_out={tmp_path}",
            str(REPO / "proto" / "c4g" / "v1" / "c4g.proto"),
        ],
        check=True,
        timeout=120,
    )
    for name in ("c4g_pb2.py", "c4g_pb2.pyi"):
        fresh = (tmp_path / "c4g" / "v1" / name).read_text()
        committed = (PACKAGE / "src" / "c4g_client" / "_proto" / name).read_text()
        assert committed == fresh, f"{name} is stale: run clients/python/generate-grpc"
