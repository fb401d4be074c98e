"""What a notebook shows: images and depth maps as PNG, videos inline; and the example
notebook is a valid notebook whose code parses."""

from __future__ import annotations

import ast
import base64
import json
import sys

import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import Client, _png
from conftest import PACKAGE


def test_renders_show_themselves_in_a_notebook(client: Client, clip: c4g.Clip):
    image = client.render(clip.id, 0.3, width=32, height=32)
    assert image._repr_png_() == image.png and "PNG" in repr(image)
    assert np.asarray(image).shape == (32, 32, 3)
    depth = client.render(clip.id, 0.3, width=32, height=24, format="depth")
    shown = _png.decode(depth._repr_png_(), pure=True)
    assert shown.shape == (24, 32, 1) and shown.max() > 0
    alpha = client.render(clip.id, 0.3, width=32, height=24, format="alpha")
    assert _png.decode(alpha._repr_png_()).shape[:2] == (24, 32)
    video = client.render_video(clip.id, c4g.Orbit(2.0, 10), frames=2, width=32, height=32)
    html = video._repr_html_()
    assert html.startswith("<video") and base64.b64encode(video.data).decode() in html


def test_the_quickstart_notebook_is_a_valid_notebook():
    notebook = json.loads((PACKAGE / "examples" / "quickstart.ipynb").read_text())
    assert notebook["nbformat"] == 4 and notebook["metadata"]["kernelspec"]["language"] == "python"
    code = [c for c in notebook["cells"] if c["cell_type"] == "code"]
    assert code and any(c["cell_type"] == "markdown" for c in notebook["cells"])
    for cell in code:
        assert set(cell) >= {"source", "outputs", "execution_count", "metadata"}
        ast.parse("".join(cell["source"]))
    assert "Client" in "".join("".join(c["source"]) for c in code)


def test_the_quickstart_notebook_runs_against_the_server_from_any_directory(
    server: str, monkeypatch, tmp_path
):
    """Each code cell in order, in one namespace, from a directory that is not the repository's
    (the notebook reads no files; the server's address is ``C4G_URL``): what a kernel would run
    (without Jupyter, which the tests do not need)."""
    notebook = json.loads((PACKAGE / "examples" / "quickstart.ipynb").read_text())
    monkeypatch.setenv("C4G_URL", server)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    try:
        for cell in notebook["cells"]:
            if cell["cell_type"] == "code":
                exec(compile("".join(cell["source"]), "quickstart.ipynb", "exec"), namespace)
    finally:
        if "client" in namespace:
            namespace["client"].close()
    assert len(namespace["sets"]) == 13 and namespace["worst"] <= 1e-3
    assert namespace["ply"].startswith(b"ply\n") and len(namespace["splat"]) % 32 == 0
    assert list(tmp_path.iterdir()) == []  # nothing written where it ran


def test_the_quickstart_notebook_names_the_extra_to_torch_needs():
    tomllib = pytest.importorskip("tomllib" if sys.version_info >= (3, 11) else "tomli")
    project = tomllib.loads((PACKAGE / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    (extra,) = [name for name, needs in extras.items() if any(n.startswith("torch") for n in needs)]
    notebook = json.loads((PACKAGE / "examples" / "quickstart.ipynb").read_text())
    text = "".join("".join(c["source"]) for c in notebook["cells"] if c["cell_type"] == "markdown")
    assert f"[{extra}]" in text and f"`{extra}` extra" in text and "to_torch()" in text
