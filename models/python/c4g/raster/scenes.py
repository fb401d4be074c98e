"""Fixture scenes for the rasterizers: small deterministic scenes with the float64 reference's render.

    python -m c4g.raster.scenes --out models/fixtures/scenes [--only NAME ...] [--footprints ellipse 3dgs]

writes one `<name>.safetensors` per scene rendered with the ellipse footprint and one
`<name>-3dgs.safetensors` per scene rendered with the 3DGS one (layout in
`models/fixtures/scenes/README.md`; the metadata's `footprint` says which). Every input is rounded to
float32 *before* the reference renders it, so a float32 rasterizer sees exactly the scene the reference
saw. A scene is only kept when the render stays clear of the forward model's discontinuities (the
3-sigma cut, the 1/255 cut, the transmittance stop, near/far, depth order, the 3DGS tile range and its
positive-exponent skip; see `reference.Margins`): otherwise a float32 rounding could flip a
pixel (or, for a tile range, a row of pixels) by up to ~1e-2 and no tight tolerance would hold. Random
scenes retry with the next seed until they are clear, for each footprint on its own.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from safetensors.numpy import save_file

from .reference import FOOTPRINTS, Camera, Margins, render

# The smallest margins a kept scene may have. Float32 errors are ~1e-5 in d² near the cut, ~1e-5
# relative in alpha and transmittance, ~3e-7 relative in depth, ~1e-4 pixels in a 3DGS radius or tile
# end (the radius at ~1e-6 relative) and ~1e-6 relative in the expanded quadratic form: these leave a
# factor of ten or more.
MIN_MARGINS = Margins(d2=1e-4, alpha=1e-4, transmittance=1e-4, near_far=1e-4, depth_order=5e-6, tiles=1e-3, power=1e-4)


@dataclass
class Scene:
    description: str
    positions: np.ndarray
    scales: np.ndarray
    rotations: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    intrinsics: tuple[float, float, float, float]
    size: tuple[int, int]
    world_to_camera: np.ndarray
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    features: np.ndarray | None = None


def f32(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float32)


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """World-to-camera [4, 4] of a camera at `eye` looking at `target` (OpenCV axes: y down)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(up, fwd)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    rot = np.stack([right, down, fwd])  # rows: camera axes in world coordinates
    view = np.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye
    return view


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def cloud(seed: int) -> Scene:
    rng = np.random.default_rng(seed)
    n = 500
    return Scene(
        description="500 anisotropic Gaussians with 5 feature channels around the origin, seen from a "
        "rotated and translated camera with a principal point off the image centre",
        positions=rng.uniform(-1.0, 1.0, (n, 3)) * [1.2, 0.9, 0.8],
        scales=np.exp(rng.uniform(np.log(0.008), np.log(0.12), (n, 3))),
        rotations=random_rotations(rng, n),
        opacities=rng.uniform(0.05, 1.0, n),
        colors=rng.uniform(0.0, 1.0, (n, 3)),
        features=rng.normal(size=(n, 5)),
        intrinsics=(105.0, 98.0, 71.3, 41.7),
        size=(128, 96),
        world_to_camera=look_at(eye=(0.9, -0.6, -3.2), target=(0.1, 0.05, 0.0)),
    )


def extremes(seed: int) -> Scene:
    """Gaussians the rasterizers must skip or survive, mixed with ordinary ones."""
    rng = np.random.default_rng(seed)
    rows = []  # position, scale, rotation, opacity, colour

    def add(p, s, q=(1.0, 0.0, 0.0, 0.0), o=0.8, c=None):
        # A sub-pixel jitter per seed, so that a seed whose pixels land on a cut can be retried.
        p = np.array(p, dtype=np.float64)
        p[:2] += rng.uniform(-1, 1, 2) * 0.002 * abs(p[2])
        rows.append((p, s, q, o, rng.uniform(0, 1, 3) if c is None else c))

    # Ordinary ones, so skipping never leaves an empty image.
    for _ in range(12):
        add(rng.uniform([-0.8, -0.6, 2.0], [0.8, 0.6, 4.0]), rng.uniform(0.03, 0.15, 3), random_rotations(rng, 1)[0])
    add((0.0, 0.0, -1.0), (0.5, 0.5, 0.5))  # behind the camera
    add((0.0, 0.0, 0.0), (0.5, 0.5, 0.5))  # at the camera centre
    add((0.3, 0.1, 0.005), (0.3, 0.3, 0.3), o=1.0)  # centre behind the near plane, body straddles it
    add((-0.01, 0.02, 0.0125), (0.004, 0.003, 0.02), o=0.9)  # just in front of the near plane: huge
    add((0.0, 0.0, 150.0), (40.0, 40.0, 40.0), o=1.0)  # beyond the far plane
    add((4.0, 0.2, 2.0), (1.2, 0.4, 0.4), o=0.9)  # far outside the view: the FOV clamp shapes it
    add((-0.3, -4.0, 3.0), (0.3, 1.5, 0.3), o=0.7)  # above the view, reaching into it
    add((0.2, -0.3, 2.5), (0.0, 0.0, 0.0), o=1.0)  # zero scale: a pixel-sized blob
    add((-0.5, 0.3, 2.5), (0.0, 0.2, 0.0), o=1.0)  # zero in two axes: a line
    add((0.4, 0.4, 2.2), (0.2, 0.2, 0.2), o=0.0)  # opacity 0
    add((-0.2, -0.1, 3.3), (0.15, 0.25, 0.05), o=1.0)  # opacity 1 (alpha saturates at 0.99)
    add((0.1, 0.2, 2.8), (0.1, 0.1, 0.1), q=(0.0, 0.0, 0.0, 0.0))  # zero rotation
    add((-0.1, 0.1, 2.6), (0.1, 0.05, 0.12), q=(3.0, 1.0, -2.0, 0.5))  # unnormalised rotation
    for bad in (np.nan, np.inf, -np.inf):  # every parameter non-finite once
        add((bad, 0.0, 2.0), (0.2, 0.2, 0.2))
        add((0.0, 0.0, 2.0), (0.2, bad, 0.2))
        add((0.0, 0.0, 2.0), (0.2, 0.2, 0.2), q=(1.0, 0.0, bad, 0.0))
        add((0.0, 0.0, 2.0), (0.2, 0.2, 0.2), o=bad)
        add((0.0, 0.0, 2.0), (0.2, 0.2, 0.2), c=(0.5, bad, 0.5))
    n_before_feature = len(rows)
    add((0.05, -0.05, 2.1), (0.3, 0.3, 0.3))  # its feature vector is NaN
    p, s, q, o, c = (np.array([r[k] for r in rows], dtype=np.float64) for k in range(5))
    features = rng.normal(size=(len(rows), 3))
    features[n_before_feature, 1] = np.nan
    return Scene(
        description="behind the camera, at the camera centre, straddling and just in front of the near "
        "plane, beyond the far plane, outside the view (FOV clamp), zero scales, opacity 0 and 1, zero "
        "and unnormalised rotations, NaN / +inf / -inf in every parameter and in a feature vector, "
        "among 12 ordinary Gaussians; 3 feature channels",
        positions=p,
        scales=s,
        rotations=q,
        opacities=o,
        colors=c,
        features=features,
        intrinsics=(70.0, 70.0, 48.0, 32.0),
        size=(96, 64),
        world_to_camera=np.eye(4),
    )


def fullscreen(seed: int) -> Scene:
    return Scene(
        description="one large Gaussian covering every pixel of the image",
        positions=np.array([[0.05, -0.03, 1.5]]),
        scales=np.array([[2.0, 1.6, 0.5]]),
        rotations=np.array([[0.96, 0.05, -0.1, 0.25]]),
        opacities=np.array([0.85]),
        colors=np.array([[0.2, 0.7, 0.4]]),
        intrinsics=(60.0, 60.0, 32.0, 24.0),
        size=(64, 48),
        world_to_camera=np.eye(4),
    )


def stack(seed: int) -> Scene:
    """Forty nearly coincident wide Gaussians: every central pixel reaches the transmittance stop."""
    rng = np.random.default_rng(seed)
    n = 40
    p = np.column_stack([rng.normal(0, 0.03, n), rng.normal(0, 0.03, n), 2.0 + np.sort(rng.uniform(0, 0.5, n))])
    p[17] = p[16]  # an exact depth tie: drawn in index order on every side
    return Scene(
        description="40 overlapping wide Gaussians (opacity 0.6 to 1) in a depth stack: the centre "
        "reaches the transmittance stop, the rim does not; two share a position exactly (a depth tie)",
        positions=p,
        scales=rng.uniform(0.15, 0.3, (n, 3)),
        rotations=random_rotations(rng, n),
        opacities=rng.uniform(0.6, 1.0, n),
        colors=rng.uniform(0, 1, (n, 3)),
        intrinsics=(64.0, 64.0, 32.0, 24.0),
        size=(64, 48),
        world_to_camera=np.eye(4),
    )


def background(seed: int) -> Scene:
    rng = np.random.default_rng(seed)
    n = 60
    return Scene(
        description="60 Gaussians over a non-black background (0.25, 0.5, 0.75)",
        positions=rng.uniform([-1.0, -0.7, 2.5], [1.0, 0.7, 5.0], (n, 3)),
        scales=rng.uniform(0.02, 0.2, (n, 3)),
        rotations=random_rotations(rng, n),
        opacities=rng.uniform(0.1, 1.0, n),
        colors=rng.uniform(0, 1, (n, 3)),
        intrinsics=(75.0, 75.0, 40.0, 30.0),
        size=(80, 60),
        world_to_camera=np.eye(4),
        background=(0.25, 0.5, 0.75),
    )


def large(seed: int) -> Scene:
    """Large anisotropic Gaussians, mostly opaque, overlapping: their fringes beyond 3 sigma (alpha up to
    0.011 · opacity each, summing where they overlap) are what the two footprints disagree on."""
    rng = np.random.default_rng(seed)
    n = 14
    return Scene(
        description="14 large anisotropic Gaussians (on screen sigma about 3 to 15 pixels, opacity 0.4 to 1) "
        "overlapping in depth, with 4 feature channels: beyond 3 sigma their fringes still reach alpha "
        "above 1/255 inside their 3DGS tiles",
        positions=rng.uniform([-0.8, -0.6, 2.5], [0.8, 0.6, 4.5], (n, 3)),
        scales=np.exp(rng.uniform(np.log(0.08), np.log(0.5), (n, 3))) * [1.0, 1.0, 0.3],
        rotations=random_rotations(rng, n),
        opacities=rng.uniform(0.4, 1.0, n),
        colors=rng.uniform(0, 1, (n, 3)),
        features=rng.normal(size=(n, 4)),
        intrinsics=(80.0, 80.0, 48.0, 36.0),
        size=(96, 72),
        world_to_camera=np.eye(4),
    )


SCENES: dict[str, Callable[[int], Scene]] = {
    "cloud": cloud,
    "extremes": extremes,
    "fullscreen": fullscreen,
    "stack": stack,
    "background": background,
    "large": large,
}


def file_name(name: str, footprint: str) -> str:
    """The fixture file of scene `name` rendered with `footprint`."""
    return f"{name}.safetensors" if footprint == "ellipse" else f"{name}-{footprint}.safetensors"


def rounded(scene: Scene) -> Scene:
    """The scene as float32 would hold it (what a Rust rasterizer reads), kept as float64."""
    as64 = lambda a: None if a is None else f32(a).astype(np.float64)  # noqa: E731
    return Scene(
        description=scene.description,
        positions=as64(scene.positions),
        scales=as64(scene.scales),
        rotations=as64(scene.rotations),
        opacities=as64(scene.opacities),
        colors=as64(scene.colors),
        features=as64(scene.features),
        intrinsics=tuple(as64(scene.intrinsics)),
        size=scene.size,
        world_to_camera=as64(scene.world_to_camera),
        background=tuple(as64(scene.background)),
    )


def render_scene(scene: Scene, margins: Margins | None = None, footprint: str = "ellipse") -> dict[str, np.ndarray]:
    fx, fy, cx, cy = scene.intrinsics
    cam = Camera(fx, fy, cx, cy, scene.size[0], scene.size[1], scene.world_to_camera)
    return render(
        scene.positions,
        scene.scales,
        scene.rotations,
        scene.opacities,
        scene.colors,
        cam,
        features=scene.features,
        background=scene.background,
        margins=margins,
        footprint=footprint,
    )


def clear_of_cuts(m: Margins) -> bool:
    return all(getattr(m, k) >= getattr(MIN_MARGINS, k) for k in asdict(MIN_MARGINS))


def build(
    name: str, first_seed: int = 0, tries: int = 50, footprint: str = "ellipse"
) -> tuple[Scene, dict[str, np.ndarray], Margins, int]:
    for seed in range(first_seed, first_seed + tries):
        scene = rounded(SCENES[name](seed))
        margins = Margins()
        with np.errstate(invalid="ignore", over="ignore"):
            out = render_scene(scene, margins, footprint)
        if clear_of_cuts(margins):
            return scene, out, margins, seed
    raise RuntimeError(f"scene {name} ({footprint}): no seed in {tries} tries stays clear of the cuts")


def tensors(scene: Scene, out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    t = {
        "positions": f32(scene.positions),
        "scales": f32(scene.scales),
        "rotations": f32(scene.rotations),
        "opacities": f32(scene.opacities),
        "colors": f32(scene.colors),
        "intrinsics": f32(scene.intrinsics),
        "size": np.asarray(scene.size, dtype=np.int32),
        "world_to_camera": f32(scene.world_to_camera),
        "background": f32(scene.background),
        "rgb": f32(out["rgb"]),
        "alpha": f32(out["alpha"]),
        "depth": f32(out["depth"]),
        "expected_depth": f32(out["expected_depth"]),
    }
    if scene.features is not None:
        t["features"] = f32(scene.features)
        t["features_image"] = f32(out["features"])
    return {k: np.ascontiguousarray(v) for k, v in t.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("models/fixtures/scenes"))
    ap.add_argument("--only", nargs="*", choices=sorted(SCENES), help="scenes to write (default: all)")
    ap.add_argument("--footprints", nargs="*", choices=FOOTPRINTS, help="footprints to render (default: both)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.only or SCENES:
        for footprint in args.footprints or FOOTPRINTS:
            scene, out, margins, seed = build(name, footprint=footprint)
            meta = {
                "description": scene.description,
                "seed": str(seed),
                "footprint": footprint,
                "generator": "python -m c4g.raster.scenes (models/python/c4g/raster/scenes.py)",
                "margins": json.dumps({k: float(v) for k, v in asdict(margins).items()}),
            }
            file = file_name(name, footprint)
            save_file(tensors(scene, out), str(args.out / file), metadata=meta)
            covered = float((out["alpha"] > 0).mean())
            print(f"{file}: seed {seed}, {len(scene.opacities)} Gaussians, {scene.size[0]}x{scene.size[1]}, "
                  f"{covered:.0%} covered, margins " + ", ".join(f"{k}={v:.2g}" for k, v in asdict(margins).items()))


if __name__ == "__main__":
    main()
