"""Fixtures: the package from ``src/`` (no install needed), the real server binary on a free
port with a throwaway store, c4g-tiny's test clip uploaded once, the tiny refiner worker and a
fit worker.

The server is the one the end-to-end tests run (``target/debug/c4g-server``, built by
``cargo build --workspace --bins``; ``C4G_BIN_DIR`` points elsewhere). It is started from the
repository root with ``scripts/env.sh`` sourced (ONNX Runtime's library), prints
``listening on ADDR``, and is ready when ``GET /ready`` answers 200.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

import httpx
import pytest

HERE = Path(__file__).resolve().parent
PACKAGE = HERE.parent
REPO = PACKAGE.parent.parent
sys.path.insert(0, str(PACKAGE / "src"))

from c4g_client import Client, Clip  # noqa: E402

BIN_DIR = Path(os.environ.get("C4G_BIN_DIR", REPO / "target" / "debug"))
TEST_CLIP = REPO / "models" / "c4g-tiny" / "test-clips" / "seed-2000000"


def binary(name: str) -> Path:
    path = BIN_DIR / name
    if not path.exists():
        pytest.fail(
            f"{path} is missing: build it with `cargo build --workspace --bins "
            "--features c4g-renderer/gpu` (or set C4G_BIN_DIR)"
        )
    return path


class Process:
    """A child process started through ``scripts/env.sh``, its stderr kept in a file so a
    failure can show it, ended (SIGTERM, then SIGKILL) at teardown."""

    def __init__(self, argv: List[str], log: Path, env: dict) -> None:
        self.log = log
        self._log_file = open(log, "wb")
        command = 'source scripts/env.sh && exec "$@"'
        self.process = subprocess.Popen(
            ["bash", "-c", command, "c4g-test", *argv],
            cwd=REPO,
            env={**os.environ, **env},
            stdout=subprocess.PIPE,
            stderr=self._log_file,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.put(line.decode(errors="replace").strip())

    def tail(self) -> str:
        self._log_file.flush()
        return self.log.read_text(errors="replace")[-3000:]

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log_file.close()


def start_server(work: Path, env: Optional[Dict[str, str]] = None) -> Tuple[Process, str]:
    """A server with its own store under ``work``, and its base URL once it is ready."""
    proc = Process(
        [str(binary("c4g-server"))],
        work / "server.log",
        {"C4G_LISTEN": "127.0.0.1:0", "C4G_STORE_DIR": str(work / "store"), **(env or {})},
    )
    try:
        address = None
        deadline = time.monotonic() + 120
        while address is None and time.monotonic() < deadline:
            if proc.process.poll() is not None:
                pytest.fail(f"the server exited ({proc.process.returncode}):\n{proc.tail()}")
            try:
                line = proc.lines.get(timeout=0.5)
            except queue.Empty:
                continue
            if line.startswith("listening on "):
                address = line.split()[-1]
        if address is None:
            pytest.fail(f"the server never said where it listens:\n{proc.tail()}")
        url = f"http://{address}"
        while time.monotonic() < deadline:
            try:
                if httpx.get(url + "/ready", timeout=5).status_code == 200:
                    return proc, url
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        pytest.fail(f"the server was not ready after 120 s:\n{proc.tail()}")
    except BaseException:
        proc.stop()
        raise


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The base URL of a fresh server (default settings, its own store)."""
    proc, url = start_server(tmp_path_factory.mktemp("server"))
    try:
        yield url
    finally:
        proc.stop()


@pytest.fixture(scope="session")
def client(server: str) -> Iterator[Client]:
    with Client(server) as c:
        yield c


@pytest.fixture(scope="session")
def frames() -> List[Path]:
    """The test clip's seven frames (0.1 s apart), in order."""
    return sorted(TEST_CLIP.glob("frame-*.png"))


@pytest.fixture(scope="session")
def clip(client: Client, frames: List[Path]) -> Clip:
    """c4g-tiny's test clip, uploaded once as ``frame`` parts at 10 fps."""
    return client.upload(frames, fps=10)


@pytest.fixture()
def refiner(server: str, tmp_path: Path) -> Iterator[Process]:
    """The tiny refinement worker (random weights: it refines nothing, the path works)."""
    proc = Process(
        [str(binary("c4g-refiner")), "--server", server, "--name", "w1", "--intra-op-threads", "1"],
        tmp_path / "refiner.log",
        {},
    )
    try:
        yield proc
    finally:
        proc.stop()


@pytest.fixture(scope="module")
def fitter(server: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Process]:
    """A fit worker (``c4g-fitter``): it takes the server's fit jobs while the module runs."""
    proc = Process(
        [str(binary("c4g-fitter")), "--server", server, "--name", "f1"],
        tmp_path_factory.mktemp("fitter") / "fitter.log",
        {},
    )
    try:
        yield proc
    finally:
        proc.stop()
