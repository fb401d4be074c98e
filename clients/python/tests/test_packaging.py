"""The package as users get it: build-wheel makes a wheel that declares only httpx and numpy
(gRPC and PyTorch as extras), carries the typed marker and the gRPC messages, and installs and
imports in a fresh environment."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

from conftest import PACKAGE


def test_build_wheel_makes_an_installable_typed_wheel(tmp_path: Path):
    subprocess.run(
        [str(PACKAGE / "build-wheel"), str(tmp_path / "dist")],
        check=True,
        capture_output=True,
        timeout=300,
        env={**os.environ, "PYTHON": sys.executable},
    )
    (wheel,) = (tmp_path / "dist").glob("c4g_client-*-py3-none-any.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        metadata = z.read(next(n for n in names if n.endswith("METADATA"))).decode()
    assert {"c4g_client/py.typed", "c4g_client/_proto/c4g_pb2.py", "c4g_client/_c4gv.py"} <= names
    requires = [line.split(": ", 1)[1] for line in metadata.splitlines() if line.startswith("Requires-Dist")]
    assert sorted(r for r in requires if "extra ==" not in r) == ["httpx>=0.24", "numpy>=1.22"]
    assert {"grpc", "torch"} <= {
        line.split(": ", 1)[1] for line in metadata.splitlines() if line.startswith("Provides-Extra")
    }

    # A fresh environment that sees this one's numpy and httpx (a .pth file), and the wheel
    # installed into it.
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=False)
    python = env_dir / "bin" / "python"
    purelib = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    Path(purelib, "outer.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(python),
            "install",
            "-q",
            "--no-deps",
            "--no-index",
            str(wheel),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    clean = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run(
        [
            str(python),
            "-c",
            "import c4g_client; print(c4g_client.__file__, c4g_client.__version__, c4g_client.Client)",
        ],
        check=True,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
        env=clean,
    ).stdout
    assert str(env_dir) in out and "0.1.0" in out
