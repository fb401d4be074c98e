"""What a fit buys on c4g-tiny's synthetic test clips, which have ground truth: held-out
interpolated frames and novel views, fitted against feed-forward, through the service itself.

    python -m c4g.eval.fit_synthetic [--bin target/release] [--preset fast] [--steps N]
                                     [--cameras given|recovered|none]

Starts `c4g-server` (the default model) and one `c4g-fitter` on a temporary store, and for each
clip in `models/c4g-tiny/test-clips/`: uploads its 7 frames with their times and, by default,
their cameras (the clip's own, in the model's frame: a user who has cameras gives them; the fit
trains at its frames' input cameras, and these clips' cameras turn), fits with
`holdout_every` 2 (so the fit trains on the context frames 0, 2, 4, 6 and never sees the
interpolated targets 1, 3, 5: the same split the model's own evaluation uses), then renders both
scenes (`"scene": "feed-forward"` and `"fitted"`) at every target time, at the input camera (the
interpolated frames) and at the clip's novel cameras, and scores them against the ground truth
frames (PSNR on 8-bit RGB, the service's PNGs against the clip's). A fit that wrecks geometry
shows as novel views below the feed-forward answer's.

`--cameras none` uploads without cameras, as a user who has none does: the fit then assumes the
still camera the service assumes for such a clip (the identity at every time), so on a clip whose
camera turns it explains the turn as the scene's motion, and its renders at the true cameras
(which the scores use) are wrong by that turn. It measures what an unknown moving camera costs.
`--cameras recovered` uploads without cameras, then recovers them (`POST
/v1/clips/{id}/cameras/recover`) before the fit, which then trains at the recovered cameras: what
a user without cameras can do about it, as good as the model's geometry.
"""

from __future__ import annotations

import argparse
import io
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import requests
from PIL import Image

REPO = Path(__file__).resolve().parents[4]
CLIPS = REPO / "models/c4g-tiny/test-clips"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def rows(matrix: list[list[float]]) -> list[float]:
    return [v for row in matrix for v in row]


def wait_ready(url: str, limit: float = 120.0) -> None:
    deadline = time.time() + limit
    while time.time() < deadline:
        try:
            if requests.get(f"{url}/ready", timeout=2).status_code == 200:
                return
        except requests.RequestException:
            pass
        time.sleep(0.5)
    raise RuntimeError("the server never became ready")


def render(url: str, clip: str, t: float, camera: dict, scene: str, size: int) -> np.ndarray:
    body = {"t": t, "width": size, "height": size, "camera": camera, "scene": scene}
    r = requests.post(f"{url}/v1/clips/{clip}/render", json=body, timeout=120)
    r.raise_for_status()
    assert r.headers["x-c4g-scene"] == scene
    return np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"))


def measure(url: str, folder: Path, fit: dict, cameras: str) -> dict:
    meta = json.loads((folder / "clip.json").read_text())
    frames = [folder / f for f in meta["frames"]]
    files = [("frame", (f.name, f.read_bytes(), "image/png")) for f in frames]
    data = {"timestamps": ",".join(str(t) for t in meta["times"]), "stride": "2"}
    k = meta["intrinsics_normalised"]
    intrinsics = {"fx": k[0], "fy": k[1], "cx": k[2], "cy": k[3]}
    if cameras == "given":
        given = [{"world_to_camera": rows(m), "intrinsics": intrinsics} for m in meta["world_to_camera_model"]]
        data["cameras"] = json.dumps(given)
    r = requests.post(f"{url}/v1/clips", files=files, data=data, timeout=300)
    r.raise_for_status()
    clip = r.json()["id"]
    started = time.time()
    if cameras == "recovered":
        requests.post(f"{url}/v1/clips/{clip}/cameras/recover", json={}, timeout=300).raise_for_status()
    job = requests.post(f"{url}/v1/clips/{clip}/fit", json=fit, timeout=60).json()
    while True:
        record = requests.get(f"{url}/v1/jobs/{job['id']}", timeout=30).json()
        if record["state"] in ("done", "failed", "cancelled"):
            break
        time.sleep(0.5)
    if record["state"] != "done":
        raise RuntimeError(f"{folder.name}: the fit ended {record['state']}: {record.get('error')}")
    fitted = requests.get(f"{url}/v1/clips/{clip}", timeout=30).json()["fitted"]
    size = np.asarray(Image.open(frames[0])).shape[0]
    scores: dict[str, dict[str, list[float]]] = {}
    for scene in ("feed-forward", "fitted"):
        held, novel = [], []
        for j, target in enumerate(meta["targets"]):
            t = meta["times"][target]
            truth = np.asarray(Image.open(frames[target]).convert("RGB"))
            camera = {"world_to_camera": rows(meta["world_to_camera_model"][target]), "intrinsics": intrinsics}
            held.append(psnr(render(url, clip, t, camera, scene, size), truth))
            truth = np.asarray(Image.open(folder / f"novel-{j:02d}.png").convert("RGB"))
            camera = {"world_to_camera": rows(meta["novel_world_to_camera_model"][j]), "intrinsics": intrinsics}
            novel.append(psnr(render(url, clip, t, camera, scene, size), truth))
        scores[scene] = {"held_out": held, "novel": novel}
    return {
        "clip": folder.name,
        "seconds": round(time.time() - started, 1),
        "gaussians": fitted["gaussians"],
        "static": fitted["static_gaussians"],
        "holdout_frames": fitted["holdout_frames"],
        **{f"{scene}_{kind}": round(float(np.mean(v)), 2) for scene, d in scores.items() for kind, v in d.items()},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.eval.fit_synthetic", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", type=lambda p: Path(p).resolve(), default=REPO / "target/release", help="where c4g-server and c4g-fitter are")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--cameras", choices=("given", "recovered", "none"), default="given", help="upload the clips' cameras; or none, recovered before the fit; or none at all (the still camera is assumed)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="another field of the fit request (JSON value), e.g. max_gaussians=2000")
    args = ap.parse_args(argv)
    fit = {"preset": args.preset, "holdout_every": 2, "resolution": 64}
    if args.steps is not None:
        fit["steps"] = args.steps
    for item in args.set:
        field, value = item.split("=", 1)
        fit[field] = json.loads(value)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as store:
        env = {"C4G_LISTEN": f"127.0.0.1:{port}", "C4G_STORE_DIR": store, "RUST_LOG": "warn"}
        import os

        server = subprocess.Popen([str(args.bin / "c4g-server")], env={**os.environ, **env}, cwd=REPO)
        fitter = None
        try:
            wait_ready(url)
            fitter = subprocess.Popen([str(args.bin / "c4g-fitter"), "--server", url, "--name", "eval"], cwd=REPO)
            results = [measure(url, folder, fit, args.cameras) for folder in sorted(CLIPS.iterdir()) if (folder / "clip.json").exists()]
        finally:
            for p in (fitter, server):
                if p is not None:
                    p.terminate()
                    p.wait(timeout=60)
    print(f"# fit {json.dumps(fit)}, cameras {args.cameras}; PSNR dB against ground truth (64 x 64); machine: {os.cpu_count()} cores")
    for r in results:
        print(json.dumps(r))
    mean = lambda key: np.mean([r[key] for r in results])  # noqa: E731
    print(
        f"mean: held-out feed-forward {mean('feed-forward_held_out'):.2f}, fitted {mean('fitted_held_out'):.2f}; "
        f"novel feed-forward {mean('feed-forward_novel'):.2f}, fitted {mean('fitted_novel'):.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
