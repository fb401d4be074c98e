"""The paper's evaluation protocols against a running service: point tracking (TAP-Vid) and novel
views at held-out times.

    scripts/eval --server http://127.0.0.1:8080 models/fixtures/eval [--json out.json] [--markdown out.md]

Input: clip folders (or a folder of them) in `c4g.eval.fixtures`' layout: `tracks.npz` (a TAP-Vid
style file, `c4g.eval.tapvid`), optional `cameras.json` (the upload's given cameras) and optional
`transforms.json` (posed frames: times, cameras, context and held-out frames, co-visibility masks).
A TAP-Vid pickle is read too, behind `--allow-pickle` (it can run code; see `c4g.eval.tapvid`).

Per clip:
1. **Upload** every frame (multipart `frame` parts, PNG) with their times (`timestamps`) and given
   cameras (`cameras`; built from `transforms.json` when there is no `cameras.json`). When the folder
   declares its context frames (`train_filenames`), the upload asks for exactly those (`start`, `end`
   at the first and last, `max_frames` their count: the server spreads that many evenly, as the
   fixtures' default 0, 3, 7, 10 is) and the run stops if the server's `context_times` differ;
   otherwise the server picks. Every frame is sent, but the service encodes only its context frames:
   the others are held out from it as surely as if they had stayed here.
2. **Tracks**: each track with a query frame inside the context span is queried there (pixel
   position from the ground truth), `POST /v1/clips/{id}/tracks` at every frame time inside the span
   (targets outside it are refused by design, so frames outside are not scored). Scored with
   TAP-Vid's query-first metrics (`c4g.eval.tapvid`: delta_avg over 1-16 px at 256 x 256, occlusion
   accuracy, average Jaccard), separately at **context** times (the context frames after the query)
   and **interpolated** times (frames between context frames), against two LK baselines
   (`c4g.eval.lk_baseline`): **LK, all frames** (every input frame, more than the service encoded) and
   **LK, context frames** (only the frames the service encoded; linear between them).
3. **Novel views** (with `transforms.json`): each held-out frame rendered at its own camera and time
   (`POST /v1/clips/{id}/render`, its camera mapped into the clip's model frame: relative to the
   first context camera, translations divided by the clip's `cameras.scale`, and held to the
   server's own context cameras to 1e-4), PSNR and SSIM (`c4g.raster.metrics`) inside its
   co-visibility mask; the context frames' renders over the whole frame beside them
   (reconstruction, not novel). Baseline: the cross-fade of the two neighbouring context frames,
   linear in time (what a viewer could show without any 3D), scored in the same masks.
Means over clips (as TAP-Vid averages over videos) per world (the part of a clip's name before its
first '-') and over all. Beside TAP-Vid's numbers, each method's median *displacement ratio* (how
far it moved a point from its query over how far the point truly moved, pooled over the clips),
which says whether a tracker under- or overshoots. Prints Markdown tables; `--json` writes
everything, `--markdown` the tables. The clip is deleted afterwards unless `--keep`.

Two things the ground truth and the service see differently, both small here and both left as the
service defines them: at interpolated times the service reports positions in the input camera
interpolated between context cameras, the ground truth in the true camera there; and the service's
pixels are those of its view of the input frame (a centre square crop), so only square videos are
taken (a crop would move the ground truth's coordinates: resize or crop such videos first).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
from PIL import Image

from c4g.raster.metrics import psnr, ssim

from . import lk_baseline, tapvid

SERVICE = "c4g (Gaussian trajectories)"
LK_ALL = "LK, all frames"
LK_CONTEXT = "LK, context frames (linear between)"
CROSSFADE = "cross-fade of neighbouring context frames"
TIME_TOLERANCE = 1e-6
CAMERA_TOLERANCE = 1e-4
QUERY_CHUNK = 1024
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
FIXTURES = Path(__file__).resolve().parents[3] / "fixtures" / "eval"


@dataclass
class Clip:
    """One clip to evaluate: its tracks and, where the folder has them, cameras and posed frames."""

    name: str
    tracks: tapvid.TrackFile
    frames_png: list[bytes]
    cameras: list[dict] | None = None  # the upload's JSON list, one per frame
    context: list[int] | None = None  # declared context frames
    held_out: list[int] = field(default_factory=list)
    masks: dict[int, np.ndarray] = field(default_factory=dict)  # held-out frame → bool [H, W]
    world_to_camera: np.ndarray | None = None  # [T, 4, 4] OpenCV, the given world's units
    intrinsics: dict | None = None  # fractions

    @property
    def times(self) -> np.ndarray:
        return self.tracks.times


def _png(pixels: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG")
    return buf.getvalue()


def _decode(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def _posed(clip: Clip, folder: Path, transforms: dict) -> None:
    """Reads a `transforms.json`'s frames, cameras, split and masks into `clip`."""
    frames = sorted(transforms["frames"], key=lambda f: f["time"])
    if len(frames) != len(clip.times) or not np.allclose([f["time"] for f in frames], clip.times, atol=TIME_TOLERANCE):
        raise ValueError(f"{folder}: transforms.json's frame times differ from tracks.npz's")
    index = {f["file_path"]: i for i, f in enumerate(frames)}
    clip.frames_png = [(folder / f["file_path"]).read_bytes() for f in frames]
    clip.world_to_camera = np.stack([np.linalg.inv(np.asarray(f["transform_matrix"], np.float64) @ _CV_TO_GL) for f in frames])
    w, h = transforms["w"], transforms["h"]
    clip.intrinsics = {"fx": transforms["fl_x"] / w, "fy": transforms["fl_y"] / h, "cx": transforms["cx"] / w, "cy": transforms["cy"] / h}
    if "train_filenames" in transforms:
        clip.context = sorted(index[n] for n in transforms["train_filenames"])
    clip.held_out = sorted(index[n] for n in transforms.get("test_filenames", []))
    for i in clip.held_out:
        path = frames[i].get("mask_path")
        clip.masks[i] = np.asarray(Image.open(folder / path).convert("L")) > 127 if path else np.ones((h, w), bool)
    if clip.cameras is None:
        clip.cameras = [{"world_to_camera": [float(v) for v in m.ravel()], "intrinsics": clip.intrinsics} for m in clip.world_to_camera]


def load_clip(folder: Path) -> Clip:
    """A clip folder in `c4g.eval.fixtures`' layout."""
    (name, tracks), = tapvid.load(folder / "tracks.npz").items()
    clip = Clip(name, tracks, [_png(f) for f in tracks.video])
    if (folder / "cameras.json").exists():
        clip.cameras = json.loads((folder / "cameras.json").read_text())
    if (folder / "transforms.json").exists():
        _posed(clip, folder, json.loads((folder / "transforms.json").read_text()))
    return clip


def find_clips(paths: list[Path], allow_pickle: bool = False) -> list[Clip]:
    """Clips from clip folders, folders of clip folders, and track files (`.npz`, `.pkl`)."""
    clips = []
    for path in paths:
        if path.is_file():
            clips += [Clip(n, t, [_png(f) for f in t.video]) for n, t in tapvid.load(path, allow_pickle).items()]
        elif (path / "tracks.npz").exists():
            clips.append(load_clip(path))
        else:
            inner = sorted(p for p in path.iterdir() if (p / "tracks.npz").exists())
            if not inner:
                raise ValueError(f"{path}: no tracks.npz in it or in its folders")
            clips += [load_clip(p) for p in inner]
    return clips


class Service:
    """The few calls the protocols make, over httpx (any transport: tests pass a fake one)."""

    def __init__(self, url: str, api_key: str | None = None, transport: httpx.BaseTransport | None = None, timeout: float = 300.0):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.Client(base_url=url, headers=headers, transport=transport, timeout=timeout)

    def _ok(self, r: httpx.Response) -> httpx.Response:
        if r.status_code >= 400:
            raise RuntimeError(f"{r.request.method} {r.request.url.path}: {r.status_code} {r.text[:500]}")
        return r

    def model(self) -> dict:
        return self._ok(self.http.get("/v1/models")).json()

    def upload(self, clip: Clip) -> dict:
        data = {"timestamps": ",".join(repr(float(t)) for t in clip.times)}
        if clip.cameras is not None:
            data["cameras"] = json.dumps(clip.cameras)
        if clip.context is not None:
            data.update(start=repr(float(clip.times[clip.context[0]])), end=repr(float(clip.times[clip.context[-1]])), max_frames=str(len(clip.context)))
        files = [("frame", (f"{i:04d}.png", png, "image/png")) for i, png in enumerate(clip.frames_png)]
        return self._ok(self.http.post("/v1/clips", data=data, files=files)).json()

    def tracks(self, clip_id: str, queries: list[dict], times: list[float], width: int, height: int) -> list[dict]:
        out = []
        for start in range(0, len(queries), QUERY_CHUNK):
            body = {"queries": queries[start : start + QUERY_CHUNK], "times": times, "width": width, "height": height}
            out += self._ok(self.http.post(f"/v1/clips/{clip_id}/tracks", json=body)).json()["tracks"]
        return out

    def render(self, clip_id: str, t: float, world_to_camera: np.ndarray, intrinsics: dict, width: int, height: int) -> np.ndarray:
        body = {
            "t": float(t),
            "camera": {"world_to_camera": [float(v) for v in world_to_camera.ravel()], "intrinsics": intrinsics},
            "width": width,
            "height": height,
            "format": "png",
        }
        return _decode(self._ok(self.http.post(f"/v1/clips/{clip_id}/render", json=body)).content)

    def delete(self, clip_id: str) -> None:
        self._ok(self.http.delete(f"/v1/clips/{clip_id}"))


def frame_splits(times: np.ndarray, context_times: list[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(context frame indices, context mask [T], interpolated mask [T]): interpolated frames lie
    strictly between the first and last context time and are not context frames."""
    context = np.array([int(np.argmin(np.abs(times - t))) for t in context_times])
    if np.any(np.abs(times[context] - np.asarray(context_times)) > TIME_TOLERANCE):
        raise ValueError(f"context times {context_times} are not frame times {times.tolist()}")
    is_context = np.zeros(len(times), bool)
    is_context[context] = True
    in_span = (times >= times[context[0]] - TIME_TOLERANCE) & (times <= times[context[-1]] + TIME_TOLERANCE)
    return context, is_context, in_span & ~is_context


def service_tracks(service: Service, clip_id: str, clip: Clip, query: np.ndarray, in_span: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The service's tracks of the queried points, as [N, T, 2] pixels and [N, T] occlusion (frames
    outside the span, and tracks whose query pixel shows nothing, predicted occluded)."""
    px = clip.tracks.pixels()
    n, t = query.shape[0], len(clip.times)
    points = np.repeat(px[np.arange(n), np.maximum(query, 0)][:, None, :], t, axis=1)
    occluded = np.ones((n, t), bool)
    asked = np.flatnonzero(query >= 0)
    if len(asked) == 0:
        return points, occluded
    queries = [{"t": float(clip.times[query[k]]), "x": float(px[k, query[k], 0]), "y": float(px[k, query[k], 1])} for k in asked]
    times = [float(v) for v in clip.times[in_span]]
    width, height = clip.tracks.size
    answered = service.tracks(clip_id, queries, times, width, height)
    for k, track in zip(asked, answered):
        for p in track.get("points", []):
            f = int(np.argmin(np.abs(clip.times - p["t"])))
            points[k, f] = (p["x"], p["y"])
            occluded[k, f] = not p["visible"]
    return points, occluded


def score_tracks(clip: Clip, context: np.ndarray, is_context: np.ndarray, interpolated: np.ndarray, predictions: dict[str, tuple[np.ndarray, np.ndarray]], query: np.ndarray) -> dict:
    """TAP-Vid metrics of each method's [N, T, 2] pixel / [N, T] occlusion predictions, per split."""
    scale = np.array(clip.tracks.size, np.float64)
    out = {}
    for method, (points, occluded) in predictions.items():
        out[method] = {
            split: tapvid.metrics(clip.tracks.points, clip.tracks.occluded, points / scale, occluded, query, frames)
            for split, frames in (("context", is_context), ("interpolated", interpolated))
        }
    return out


def displacement_ratios(clip: Clip, points: np.ndarray, query: np.ndarray, in_span: np.ndarray) -> list[float]:
    """How far a method moves each point from its query position, over how far the true point
    moved: one ratio per scored visible point (after its query, inside the span) whose true
    motion is over one input pixel. Not a TAP-Vid metric: it tells too little motion (< 1) from
    too much (> 1), which the thresholds cannot."""
    truth = clip.tracks.pixels()
    out = []
    for n in np.flatnonzero(query >= 0):
        start = truth[n, query[n]]
        frames = np.flatnonzero(in_span & (np.arange(len(clip.times)) > query[n]) & ~clip.tracks.occluded[n])
        moved = np.linalg.norm(truth[n, frames] - start, axis=1)
        keep = moved > 1.0
        out += (np.linalg.norm(points[n, frames[keep]] - start, axis=1) / moved[keep]).tolist()
    return out


def model_frame_cameras(clip: Clip, context: np.ndarray, scale: float) -> np.ndarray:
    """Every frame's camera [T, 4, 4] in the clip's model frame (the service's rule,
    `docs/api.md`): relative to the first context camera, translations divided by `scale`."""
    first = clip.world_to_camera[context[0]]
    out = clip.world_to_camera @ np.linalg.inv(first)
    out[:, :3, 3] /= scale
    return out


def score_views(service: Service, clip_id: str, clip: Clip, answer: dict, context: np.ndarray) -> dict:
    """PSNR / SSIM of the service's renders at held-out frames (in their masks) and context frames
    (whole frames), and of the cross-fade baseline at the held-out frames."""
    given = answer.get("cameras") or {}
    scale = float(given.get("scale", 1.0))
    cameras = model_frame_cameras(clip, context, scale)
    for k, stored in zip(context, given.get("frames", [])):
        gap = np.abs(cameras[k].ravel() - np.asarray(stored["world_to_camera"])).max()
        if gap > CAMERA_TOLERANCE:
            raise RuntimeError(f"{clip.name}: context camera {k} maps to the model frame {gap:.2e} away from the server's: the frame rule differs")
    truth = clip.tracks.video.astype(np.float64) / 255
    width, height = clip.tracks.size
    rows: dict[str, dict[str, list]] = {SERVICE: {"held_out": [], "context": []}, CROSSFADE: {"held_out": []}}
    for f in clip.held_out:
        if not context[0] < f < context[-1]:
            continue
        mask = clip.masks[f]
        image = service.render(clip_id, clip.times[f], cameras[f], clip.intrinsics, width, height).astype(np.float64) / 255
        right = int(np.searchsorted(context, f))
        a, b = context[right - 1], context[right]
        w = (clip.times[f] - clip.times[a]) / (clip.times[b] - clip.times[a])
        fade = (1 - w) * truth[a] + w * truth[b]
        for method, img in ((SERVICE, image), (CROSSFADE, fade)):
            rows[method]["held_out"].append({"frame": int(f), "psnr": psnr(img, truth[f], mask), "ssim": ssim(img, truth[f], mask), "mask_fraction": float(mask.mean())})
    for f in context:
        image = service.render(clip_id, clip.times[f], cameras[f], clip.intrinsics, width, height).astype(np.float64) / 255
        rows[SERVICE]["context"].append({"frame": int(f), "psnr": psnr(image, truth[f]), "ssim": ssim(image, truth[f]), "mask_fraction": 1.0})
    out = {}
    for method, splits in rows.items():
        out[method] = {}
        for split, frames in splits.items():
            mean = {k: float(np.mean([r[k] for r in frames])) if frames else float("nan") for k in ("psnr", "ssim", "mask_fraction")}
            out[method][split] = {**mean, "frames": frames}
    return out


def evaluate_clip(service: Service, clip: Clip, keep: bool = False) -> dict:
    """Uploads, tracks, renders and scores one clip (the module docstring's protocol)."""
    width, height = clip.tracks.size
    if width != height:
        raise ValueError(f"{clip.name}: {width}x{height} frames; the protocols take square ones (module docstring)")
    started = time.perf_counter()
    answer = service.upload(clip)
    try:
        context_times = answer["context_times"]
        declared = clip.times[clip.context] if clip.context is not None else None
        if declared is not None and (len(declared) != len(context_times) or not np.allclose(declared, context_times, atol=TIME_TOLERANCE)):
            raise RuntimeError(f"{clip.name}: the server chose context times {context_times}, the folder declares {clip.times[clip.context].tolist()}")
        context, is_context, interpolated = frame_splits(clip.times, context_times)
        in_span = is_context | interpolated
        # A query outside the span cannot be asked; such a track is not scored by any method.
        query = np.where((clip.tracks.query_frame >= 0) & in_span[np.maximum(clip.tracks.query_frame, 0)], clip.tracks.query_frame, -1)
        px = clip.tracks.pixels()
        query_xy = px[np.arange(len(query)), np.maximum(query, 0)]
        predictions = {
            SERVICE: service_tracks(service, answer["id"], clip, query, in_span),
            LK_ALL: lk_baseline.track(clip.tracks.video, query, query_xy),
            LK_CONTEXT: lk_baseline.track_context_only(clip.tracks.video, context, query, query_xy),
        }
        result = {
            "clip": clip.name,
            "id": answer["id"],
            "context_frames": context.tolist(),
            "context_times": context_times,
            "queried_tracks": int((query >= 0).sum()),
            "tracking": score_tracks(clip, context, is_context, interpolated, predictions, query),
            "displacement_ratios": {m: displacement_ratios(clip, p, query, in_span) for m, (p, _) in predictions.items()},
        }
        if clip.world_to_camera is not None and clip.held_out:
            result["views"] = score_views(service, answer["id"], clip, answer, context)
        result["seconds"] = round(time.perf_counter() - started, 2)
        return result
    finally:
        if not keep:
            service.delete(answer["id"])


def summarise(results: list[dict]) -> dict:
    """Means over clips, per group (world) and over all."""
    groups: dict[str, list[dict]] = {}
    for r in results:
        groups.setdefault(r["clip"].split("-")[0], []).append(r)
    if len(groups) > 1:
        groups["all"] = results
    out = {}
    for group, rs in groups.items():
        tracking = {
            m: {s: tapvid.mean_over_videos([r["tracking"][m][s] for r in rs]) for s in ("context", "interpolated")}
            for m in rs[0]["tracking"]
        }
        views: dict = {}
        with_views = [r for r in rs if "views" in r]
        for m in with_views[0]["views"] if with_views else []:
            views[m] = {}
            for s in with_views[0]["views"][m]:
                values = [r["views"][m][s] for r in with_views]
                views[m][s] = {k: float(np.nanmean([v[k] for v in values])) for k in ("psnr", "ssim", "mask_fraction")}
                views[m][s]["frames"] = sum(len(v["frames"]) for v in values)
        motion = {}
        for m in rs[0]["displacement_ratios"]:
            pooled = [v for r in rs for v in r["displacement_ratios"][m]]
            motion[m] = {"median": float(np.median(pooled)) if pooled else float("nan"), "points": len(pooled)}
        out[group] = {"clips": len(rs), "tracking": tracking, "displacement_ratio": motion, "views": views}
    return out


def tables(summary: dict) -> str:
    """Markdown tables of the summary."""
    lines = [
        "| clips | method | times | δ_avg | occlusion acc. | AJ | δ<1 | δ<2 | δ<4 | δ<8 | δ<16 | visible points |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for group, s in summary.items():
        for method, splits in s["tracking"].items():
            for split, m in splits.items():
                deltas = " | ".join(f"{m[f'delta_{d}']:.3f}" for d in tapvid.THRESHOLDS)
                lines.append(f"| {group} ({s['clips']}) | {method} | {split} | {m['delta_avg']:.3f} | {m['occlusion_accuracy']:.3f} | {m['average_jaccard']:.3f} | {deltas} | {m['visible']} |")
    lines += ["", "| clips | method | median displacement from the query, over the true one | points |", "|---|---|---|---|"]
    for group, s in summary.items():
        for method, m in s["displacement_ratio"].items():
            lines.append(f"| {group} ({s['clips']}) | {method} | {m['median']:.2f} | {m['points']} |")
    if any(s["views"] for s in summary.values()):
        lines += ["", "| clips | method | frames | PSNR (dB) | SSIM | pixels counted | frame count |", "|---|---|---|---|---|---|---|"]
        for group, s in summary.items():
            for method, splits in s["views"].items():
                for split, m in splits.items():
                    label = "held out, co-visible pixels" if split == "held_out" else "context (reconstruction)"
                    lines.append(f"| {group} ({s['clips']}) | {method} | {label} | {m['psnr']:.2f} | {m['ssim']:.3f} | {m['mask_fraction']:.0%} | {m['frames']} |")
    return "\n".join(lines)


def machine() -> str:
    """The CPU's model name and core count, for the record."""
    name = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{name}, {os.cpu_count()} cores"


def run(service: Service, clips: list[Clip], keep: bool = False) -> dict:
    model = service.model()
    results = []
    for clip in clips:
        results.append(evaluate_clip(service, clip, keep))
        print(f"{clip.name}: {results[-1]['queried_tracks']} tracks, context frames {results[-1]['context_frames']}, {results[-1]['seconds']} s", file=sys.stderr)
    return {"model": model, "machine": machine(), "clips": results, "summary": summarise(results)}


def main(argv: list[str] | None = None, transport: httpx.BaseTransport | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", type=Path, nargs="*", default=[FIXTURES], help="clip folders, folders of them, or track files (default: the committed fixtures)")
    parser.add_argument("--server", default=os.environ.get("C4G_SERVER", "http://127.0.0.1:8080"))
    parser.add_argument("--api-key", default=os.environ.get("C4G_API_KEY"))
    parser.add_argument("--json", type=Path, help="write every number here")
    parser.add_argument("--markdown", type=Path, help="write the tables here")
    parser.add_argument("--allow-pickle", action="store_true", help="read TAP-Vid .pkl files (unpickling runs code: only for files you trust)")
    parser.add_argument("--keep", action="store_true", help="leave the uploaded clips on the server")
    parser.add_argument("--per-clip", action="store_true", help="a row per clip too, before the means")
    args = parser.parse_args(argv)
    clips = find_clips(args.paths, args.allow_pickle)
    report = run(Service(args.server, args.api_key, transport), clips, args.keep)
    shown = report["summary"]
    if args.per_clip:
        # summarise() of one clip is that clip's numbers, under its world's name: rename it.
        per_clip = {}
        for r in report["clips"]:
            name = r["clip"] if r["clip"] not in per_clip else f"{r['clip']} #{len(per_clip) + 1}"
            per_clip[name] = next(iter(summarise([r]).values()))
        shown = per_clip | shown
    text = tables(shown)
    print(text)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=float) + "\n")
    if args.markdown:
        args.markdown.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
