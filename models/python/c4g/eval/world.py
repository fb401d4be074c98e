"""A second procedural world, used only to evaluate: never trained on.

`c4g.train.synthetic` makes the training data (a textured box room, rigid or squashing clusters on
harmonic paths, a camera that orbits, pans or dollies). A model that only learned that generator
scores well on its test split and badly elsewhere; this world asks the same question with other
answers, written separately (no code of `synthetic` is used but the model's frame convention,
`normalise_to_first_camera`, which is a definition, and the rasterizer, which is the physics):

- **stage**: a ground disc and a curved backdrop (part of a cylinder) of irregularly scattered,
  flat Gaussians (no grid), textured with stripes, checkers or value noise at a random scale;
- **objects** (1-3), from families the training world does not have: a torus, a helix (thin), a
  sphere shell, a two-link arm (articulated: the second link turns about its joint), a rod (thin);
- **motions**: ballistic arcs that bounce on the ground, turns about an axis off the object's
  centre, stop-and-go (eased moves with pauses), periodic swings;
- **light**: a global brightness that changes over the clip (0.75x to 1.25x);
- **camera**: handheld (a slow drift with high-frequency shake), an arc about a point off the
  scene's centre, a crane (rising while looking at the scene), or still;
- occlusion and disocclusion happen as objects pass each other and the backdrop.

Deterministic from a seed; any seed is a clip. Frames are rendered with C4G's fixed intrinsics,
at `FPS`, for `FRAMES` frames: enough for 4 context frames 4 source frames apart. `tracks` gives
ground-truth point tracks on the objects (for `c4g.eval.fixtures`), without changing any render.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from c4g.raster.fast import dominant_ids, render_batch

FPS = 10.0
FRAMES = 17
FOCAL = 0.8767
OBJECT_FAMILIES = ("torus", "helix", "shell", "arm", "rod")
MOTIONS = ("ballistic", "offcentre", "stopgo", "swing")
CAMERAS = ("handheld", "arc", "crane", "still")


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' rotation matrix about a unit `axis`."""
    a = axis / np.linalg.norm(axis)
    c, s = math.cos(angle), math.sin(angle)
    x, y, z = a
    return np.array(
        [
            [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
            [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
            [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
        ]
    )


def _quaternion(m: np.ndarray) -> np.ndarray:
    """A rotation matrix [3, 3] → unit quaternion w, x, y, z (Shepperd's method, stable)."""
    t = np.trace(m)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _frame_from_normal(n: np.ndarray) -> np.ndarray:
    """A rotation whose third column is the unit normal `n` (flat Gaussians lie across it)."""
    n = n / np.linalg.norm(n)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, n)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(n, u), n], axis=1)


@dataclass
class Pattern:
    """A colour pattern over 2D coordinates: stripes, checkers or value noise."""

    kind: str
    scale: float
    angle: float
    colours: np.ndarray  # [2, 3]
    lattice: np.ndarray  # [16, 16] random values for the noise

    @staticmethod
    def random(rng: np.random.Generator) -> Pattern:
        base = rng.uniform(0.1, 0.9, 3)
        other = np.clip(base + rng.choice([-1, 1], 3) * rng.uniform(0.2, 0.5, 3), 0.02, 0.98)
        return Pattern(
            str(rng.choice(["stripes", "checker", "noise"])),
            float(rng.uniform(1.5, 9.0)),
            float(rng.uniform(0, math.pi)),
            np.stack([base, other]),
            rng.uniform(0, 1, (16, 16)),
        )

    def colour(self, uv: np.ndarray) -> np.ndarray:
        c, s = math.cos(self.angle), math.sin(self.angle)
        u = (uv[:, 0] * c - uv[:, 1] * s) * self.scale
        v = (uv[:, 0] * s + uv[:, 1] * c) * self.scale
        if self.kind == "stripes":
            w = 0.5 + 0.5 * np.sin(u * math.pi)
        elif self.kind == "checker":
            w = ((np.floor(u) + np.floor(v)) % 2).astype(float)
        else:  # bilinear value noise on a 16 x 16 lattice, wrapped
            x, y = u % 16, v % 16
            x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
            fx, fy = x - x0, y - y0
            g = self.lattice
            a, b = g[x0, y0], g[(x0 + 1) % 16, y0]
            c_, d = g[x0, (y0 + 1) % 16], g[(x0 + 1) % 16, (y0 + 1) % 16]
            w = (a * (1 - fx) + b * fx) * (1 - fy) + (c_ * (1 - fx) + d * fx) * fy
        return self.colours[0] * (1 - w[:, None]) + self.colours[1] * w[:, None]


@dataclass
class Part:
    """Gaussians of one rigid piece, in its own frame (rotations as matrices)."""

    means: np.ndarray
    rotations: np.ndarray  # [K, 3, 3]
    scales: np.ndarray
    opacities: np.ndarray
    colours: np.ndarray

    def placed(self, rotation: np.ndarray, translation: np.ndarray) -> Part:
        return Part(self.means @ rotation.T + translation, rotation @ self.rotations, self.scales, self.opacities, self.colours)


def _surface_gaussians(points: np.ndarray, normals: np.ndarray, uv: np.ndarray, size: float, thickness: float, pattern: Pattern) -> Part:
    k = len(points)
    return Part(
        points,
        np.stack([_frame_from_normal(n) for n in normals]),
        np.tile([size, size, thickness], (k, 1)),
        np.full(k, 0.95),
        pattern.colour(uv),
    )


def _stage(rng: np.random.Generator, count: int) -> Part:
    """A ground disc (y = 1, y pointing down) and a curved backdrop behind the scene."""
    ground_n = count // 2
    r = 3.0 * np.sqrt(rng.uniform(0, 1, ground_n))
    a = rng.uniform(0, 2 * math.pi, ground_n)
    ground = np.stack([r * np.cos(a), np.full(ground_n, 1.0), 3.0 + r * np.sin(a)], 1)
    g = _surface_gaussians(ground, np.tile([0.0, -1.0, 0.0], (ground_n, 1)), ground[:, [0, 2]] / 3, 0.13, 0.01, Pattern.random(rng))
    back_n = count - ground_n
    theta = rng.uniform(-1.1, 1.1, back_n)
    height = rng.uniform(-2.0, 1.0, back_n)
    radius = 4.0
    back = np.stack([radius * np.sin(theta), height, 3.0 + radius * np.cos(theta) - 0.5], 1)
    normals = np.stack([-np.sin(theta), np.zeros(back_n), -np.cos(theta)], 1)
    b = _surface_gaussians(back, normals, np.stack([theta, height / 3], 1), 0.14, 0.01, Pattern.random(rng))
    return Part(*(np.concatenate([getattr(g, f), getattr(b, f)]) for f in ("means", "rotations", "scales", "opacities", "colours")))


def _shape(rng: np.random.Generator, family: str, count: int, size: float) -> list[Part]:
    """One object of `family`, as parts (an arm has two), in its own frame."""
    pattern = Pattern.random(rng)
    s = rng.uniform(0, 1, count)
    t = rng.uniform(0, 1, count)
    if family == "torus":
        big, small = size, size * rng.uniform(0.25, 0.4)
        u, v = 2 * math.pi * s, 2 * math.pi * t
        centre = np.stack([np.cos(u), np.zeros(count), np.sin(u)], 1) * big
        normal = np.stack([np.cos(u) * np.cos(v), np.sin(v), np.sin(u) * np.cos(v)], 1)
        return [_surface_gaussians(centre + small * normal, normal, np.stack([s, t], 1), size * 0.12, size * 0.03, pattern)]
    if family == "shell":
        z = 2 * s - 1
        phi = 2 * math.pi * t
        normal = np.stack([np.sqrt(1 - z * z) * np.cos(phi), z, np.sqrt(1 - z * z) * np.sin(phi)], 1)
        return [_surface_gaussians(normal * size, normal, np.stack([phi / 6, z], 1), size * 0.16, size * 0.03, pattern)]
    if family == "helix":
        turns = rng.uniform(2, 4)
        a = 2 * math.pi * turns * s
        points = np.stack([np.cos(a) * size * 0.5, (s - 0.5) * size * 2, np.sin(a) * size * 0.5], 1)
        tangent = np.stack([-np.sin(a), np.full(count, 1.0 / (math.pi * turns)), np.cos(a)], 1)
        part = _surface_gaussians(points, tangent, np.stack([s, t], 1), size * 0.05, size * 0.05, pattern)
        part.scales[:, 2] = size * 0.12  # thin along the curve's direction
        return [part]
    # A rod, or the links of an arm: thin cylinders along local y.
    def rod(n: int, length: float, radius: float) -> Part:
        a = 2 * math.pi * rng.uniform(0, 1, n)
        y = rng.uniform(0, length, n)
        normal = np.stack([np.cos(a), np.zeros(n), np.sin(a)], 1)
        return _surface_gaussians(normal * radius + np.stack([np.zeros(n), y, np.zeros(n)], 1), normal, np.stack([a, y], 1), radius * 0.9, radius * 0.3, pattern)

    if family == "rod":
        r = rod(count, size * 2.2, size * 0.06)
        r.means[:, 1] -= size * 1.1
        return [r]
    half = count // 2
    return [rod(half, size * 1.1, size * 0.12), rod(count - half, size * 1.0, size * 0.1)]


@dataclass
class Thing:
    """A moving object: its parts, motion and (for an arm) joint."""

    parts: list[Part]
    family: str
    motion: str
    start: np.ndarray
    params: dict

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(rotation, translation) of the object at time t."""
        p = self.params
        if self.motion == "ballistic":
            # Thrown, falls under gravity (world y points down) to the ground (y = 1, less its
            # radius) and bounces, keeping 70% of its speed each time.
            g, floor = 6.0, 1.0 - p["radius"]
            tau, y, v = t, float(self.start[1]), float(p["vy"])
            for _ in range(32):
                hit = (-v + math.sqrt(v * v + 2 * g * max(floor - y, 0.0))) / g
                if hit >= tau or hit <= 1e-6:
                    break
                tau, y, v = tau - hit, floor, -0.7 * (v + g * hit)
            y = min(y + v * tau + 0.5 * g * tau * tau, floor)
            position = self.start + np.array([p["vx"] * t, 0.0, p["vz"] * t])
            position[1] = y
            return _rotation(p["axis"], p["spin"] * t), position
        if self.motion == "offcentre":
            # Turns about an axis through a pivot beside it: the centre sweeps an arc.
            rot = _rotation(p["axis"], p["rate"] * t)
            return rot, p["pivot"] + rot @ (self.start - p["pivot"])
        if self.motion == "stopgo":
            # Eased moves between waypoints, each followed by a pause.
            legs = p["waypoints"]
            per = p["leg"]
            k = min(int(t // per), len(legs) - 2)
            local = min(max((t - k * per) / (per * 0.6), 0.0), 1.0)
            ease = local * local * (3 - 2 * local)
            return _rotation(p["axis"], p["spin"] * (k + ease)), legs[k] * (1 - ease) + legs[k + 1] * ease
        # swing: a pendulum-like periodic sway about a point above.
        angle = p["amplitude"] * math.sin(p["rate"] * t + p["phase"])
        rot = _rotation(p["axis"], angle)
        return rot, p["hinge"] + rot @ (self.start - p["hinge"])

    def gaussians(self, t: float) -> list[Part]:
        rot, trans = self.pose(t)
        if self.family != "arm":
            return [self.parts[0].placed(rot, trans)]
        # The second link hangs from the first link's end and turns about its own joint.
        first, second = self.parts
        end = np.array([0.0, first.means[:, 1].max(), 0.0])
        bend = _rotation(np.array([0.0, 0.0, 1.0]), self.params["bend0"] + self.params["bend"] * math.sin(self.params["bend_rate"] * t))
        second_local = second.placed(bend, end)
        return [first.placed(rot, trans), second_local.placed(rot, trans)]


def _look(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-to-camera [4, 4], OpenCV axes (x right, y down, z forward), y down in the world."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(np.array([0.0, 1.0, 0.0]), forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    r = np.stack([right, down, forward])
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, -r @ eye
    return out


@dataclass
class EvalScene:
    seed: int
    stage: Part
    things: list[Thing]
    camera_kind: str
    camera_params: dict
    light: tuple[float, float]
    duration: float

    def camera(self, t: float) -> np.ndarray:
        p, s = self.camera_params, t / self.duration
        target = p["target"]
        if self.camera_kind == "handheld":
            eye = p["eye"] + p["drift"] * s
            shake = sum(a * np.sin(f * t + ph) for a, f, ph in p["shake"])
            return _look(eye + shake, target + 0.3 * shake)
        if self.camera_kind == "arc":
            angle = p["angle0"] + p["sweep"] * s
            eye = p["pivot"] + p["radius"] * np.array([math.sin(angle), -p["height"], -math.cos(angle)])
            return _look(eye, target)
        if self.camera_kind == "crane":
            return _look(p["eye"] + np.array([0.0, -p["rise"] * s, 0.0]), target)
        return _look(p["eye"], target)

    def object_ids(self) -> np.ndarray:
        """Each Gaussian's object id, in the order of `gaussians(t)`: 0 for the stage, k for the
        k-th thing."""
        counts = [len(self.stage.opacities)] + [sum(len(p.opacities) for p in thing.gaussians(0.0)) for thing in self.things]
        return np.concatenate([np.full(c, i, dtype=np.int64) for i, c in enumerate(counts)])

    def gaussians(self, t: float) -> tuple[np.ndarray, ...]:
        """(means, scales, quaternions wxyz, opacities, colours) of every Gaussian at time t."""
        parts = [self.stage] + [part for thing in self.things for part in thing.gaussians(t)]
        means = np.concatenate([p.means for p in parts])
        scales = np.concatenate([p.scales for p in parts])
        quats = np.stack([_quaternion(r) for p in parts for r in p.rotations])
        opacities = np.concatenate([p.opacities for p in parts])
        light = self.light[0] + (self.light[1] - self.light[0]) * t / self.duration
        colours = np.clip(np.concatenate([p.colours for p in parts]) * light, 0, 1)
        return means, scales, quats, opacities, colours


def make_scene(seed: int, gaussians: int = 1600) -> EvalScene:
    rng = np.random.default_rng([0xE7A1, seed])
    duration = (FRAMES - 1) / FPS
    stage = _stage(rng, gaussians // 2)
    things = []
    budget = gaussians - gaussians // 2
    count = int(rng.integers(1, 4))
    for k in range(count):
        family = str(rng.choice(OBJECT_FAMILIES))
        motion = str(rng.choice(MOTIONS))
        size = float(rng.uniform(0.25, 0.5))
        start = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-0.4, 0.6), rng.uniform(2.4, 3.6)])
        axis = rng.normal(size=3)
        params: dict = {"axis": axis / np.linalg.norm(axis), "radius": size}
        if motion == "ballistic":
            params.update(vx=rng.uniform(-0.8, 0.8), vz=rng.uniform(-0.4, 0.4), vy=rng.uniform(-3.0, -1.0), spin=rng.uniform(-3, 3))
            start[1] = rng.uniform(-0.3, 0.3)
        elif motion == "offcentre":
            params.update(pivot=start + rng.normal(size=3) * np.array([0.5, 0.2, 0.5]), rate=rng.uniform(0.6, 1.6) * rng.choice([-1, 1]))
        elif motion == "stopgo":
            waypoints = [start + rng.normal(size=3) * np.array([0.5, 0.15, 0.4]) * (i > 0) for i in range(4)]
            params.update(waypoints=waypoints, leg=duration / 3, spin=rng.uniform(-1.5, 1.5))
        else:
            params.update(hinge=start + np.array([0.0, -rng.uniform(0.8, 1.5), 0.0]), amplitude=rng.uniform(0.3, 0.7), rate=rng.uniform(2.0, 5.0), phase=rng.uniform(0, 2 * math.pi))
        params.update(bend0=rng.uniform(-0.5, 0.5), bend=rng.uniform(0.4, 1.0), bend_rate=rng.uniform(2, 5))
        share = budget // count + (budget % count if k == 0 else 0)
        things.append(Thing(_shape(rng, family, share, size), family, motion, start, params))
    kind = str(rng.choice(CAMERAS))
    target = np.array([rng.uniform(-0.3, 0.3), rng.uniform(0.0, 0.4), 3.0])
    eye = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.8, -0.2), rng.uniform(-0.6, 0.0)])
    camera = {"target": target, "eye": eye}
    if kind == "handheld":
        camera.update(drift=rng.normal(size=3) * 0.25, shake=[(rng.normal(size=3) * 0.015, rng.uniform(15, 40), rng.uniform(0, 6.3)) for _ in range(3)])
    elif kind == "arc":
        camera.update(pivot=target + np.array([rng.uniform(-0.7, 0.7), 0.0, rng.uniform(-0.5, 0.5)]), radius=float(np.linalg.norm(eye - target)), height=rng.uniform(0.1, 0.3), angle0=rng.uniform(-0.4, 0.4), sweep=rng.uniform(0.3, 0.8) * rng.choice([-1, 1]))
    elif kind == "crane":
        camera.update(rise=rng.uniform(0.3, 0.8))
    light = (float(rng.uniform(0.75, 1.1)), float(rng.uniform(0.9, 1.25)))
    return EvalScene(seed, stage, things, kind, camera, light, duration)


def render(scene: EvalScene, times: np.ndarray, size: int, cameras: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames [T, H, W, 3] in [0, 1], expected depth [T, H, W], world-to-camera [T, 4, 4]) at
    `times`, from the scene's camera unless `cameras` gives others (novel views)."""
    w2c = np.stack([scene.camera(float(t)) if cameras is None else cameras[i] for i, t in enumerate(times)])
    sets = [scene.gaussians(float(t)) for t in times]
    stack = lambda k: torch.from_numpy(np.stack([s[k] for s in sets]))  # noqa: E731
    f = FOCAL * size
    with torch.no_grad():
        out = render_batch(stack(0), stack(1), stack(2), stack(3), stack(4), (f, f, size / 2, size / 2), torch.from_numpy(w2c), size, size)
    return out["rgb"].clamp(0, 1).numpy().astype(np.float32), out["expected_depth"].numpy(), w2c


def render_object_ids(scene: EvalScene, times: np.ndarray, size: int, cameras: np.ndarray | None = None) -> np.ndarray:
    """The object id [T, H, W] (uint8, `EvalScene.object_ids`) that carries most of each pixel's
    weight, at the cameras `render` uses."""
    w2c = np.stack([scene.camera(float(t)) if cameras is None else cameras[i] for i, t in enumerate(times)])
    sets = [scene.gaussians(float(t)) for t in times]
    gaussians = tuple(np.stack([s[k] for s in sets]) for k in range(4))
    f = FOCAL * size
    return dominant_ids(gaussians, scene.object_ids(), (f, f, size / 2, size / 2), w2c, size)


# Points followed on each object for tracking evaluation (`c4g.eval.fixtures`), split over its parts.
TRACKS_PER_THING = 16


def track_points(scene: EvalScene) -> list[tuple[int, int, np.ndarray]]:
    """(thing, part, Gaussian indices into that part) of the points to track: TRACKS_PER_THING
    per object, shared between its parts.

    Chosen without drawing from any random generator, so that adding tracks changed nothing that
    `make_scene` makes or `render` draws: indices evenly spaced through a part's Gaussians, whose
    positions on the surface were themselves random draws, so they land at scattered surface points.
    A Gaussian's centre lies on its surface, and its identity holds over time: its centre at any
    time is the tracked point."""
    out = []
    for k, thing in enumerate(scene.things):
        per_part = -(-TRACKS_PER_THING // len(thing.parts))
        for p, part in enumerate(thing.parts):
            count = min(per_part, len(part.means))
            out.append((k, p, np.linspace(0, len(part.means) - 1, count).round().astype(int)))
    return out


def tracks(scene: EvalScene, times: np.ndarray, size: int, depth: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground-truth point tracks of `track_points` at `times`, seen from `w2c` [T, 4, 4] with the
    expected `depth` [T, H, W] that `render` gave for the same times and cameras: (world positions
    [T, K, 3], pixels [T, K, 2] with pixel (i, j) covering [i, i+1) x [j, j+1), visible [T, K]).

    Visibility is `c4g.train.synthetic.render_clip`'s rule, so both worlds' tracks mean the same: in
    front of the camera (z > 0.01), inside the image, and no farther than the rendered surface at
    its pixel allows (z <= 1.05 depth + 0.02)."""
    chosen = track_points(scene)
    pts = []
    for t in times:
        placed = [thing.gaussians(float(t)) for thing in scene.things]
        pts.append(np.concatenate([placed[k][p].means[idx] for k, p, idx in chosen]) if chosen else np.zeros((0, 3)))
    pts = np.stack(pts)
    f = FOCAL * size
    cam = np.einsum("tij,tkj->tki", w2c[:, :3, :3], pts) + w2c[:, None, :3, 3]
    z = np.maximum(cam[..., 2], 1e-9)
    uv = np.stack([f * cam[..., 0] / z + size / 2, f * cam[..., 1] / z + size / 2], -1)
    inside = (cam[..., 2] > 0.01) & (uv >= 0).all(-1) & (uv < size).all(-1)
    px = np.clip(uv.astype(int), 0, size - 1)
    surface = np.take_along_axis(depth.reshape(len(times), -1), px[..., 1] * size + px[..., 0], axis=1)
    return pts, uv, inside & (cam[..., 2] <= surface * 1.05 + 0.02)
