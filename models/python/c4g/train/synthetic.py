"""Procedural dynamic scenes with ground truth, for training and evaluating small C4G models.

A scene is a static room (a floor and three walls, textured, made of flat Gaussians), 1-4 moving
objects (clusters of Gaussians moving rigidly along smooth paths while turning; some also deform)
and a camera that orbits, pans, dollies or stays still. Everything is a function of time, so a clip
can be rendered at any timestamp and from any camera: context frames, target frames between them,
and novel views.

`world=2` (`make_scene(seed, world=2)`) is the wider training world of c4g-tiny v2; `world=1`
(the default) stays the world c4g-tiny was trained on, unchanged, so that model remains
reproducible. World 2 adds object families (thin sticks and cards, articulated objects bending at
a joint, more squash-and-stretch), motion families (ballistic throws that bounce on the floor,
turns about an axis off the object, stop-and-go moves; the harmonic paths stay), a handheld
camera (a still or panning camera with shake), textures (value noise at several scales, and
photographs from scikit-image's CC0 sample images), and light that changes over the clip.
`c4g.eval.world` is a separate world used only to evaluate.

Deterministic from a seed; the split is by seed range (`SPLITS`). World units are arbitrary; the
model's convention (first context camera at the origin, distance between the first and last context
cameras = 1) is applied per sample by `normalise_to_first_camera`, with a stated rule when the camera
does not move.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from c4g.raster.fast import dominant_ids, render_batch

SPLITS = {"train": range(0, 1_000_000), "validation": range(1_000_000, 1_001_000), "test": range(2_000_000, 2_001_000)}
# Every clip: FRAMES frames at FPS (media time 0 .. 1 s). Intrinsics are C4G's fixed normalised ones
# (the model predicts no cameras, so the service renders with these by default).
FRAMES = 11
FPS = 10.0
C4G_FOCAL = 0.8767
CAMERA_MOTIONS = ("orbit", "pan", "dolly", "static")
# When the camera does not move, scenes are scaled so that the median depth of the first frame is
# this (a typical baseline-to-depth ratio for the moving-camera case; see normalise_to_first_camera).
STATIC_MEDIAN_DEPTH = 2.0
MIN_BASELINE = 1e-6


def _look_at(eye: np.ndarray, target: np.ndarray, down: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """World-to-camera [4, 4], OpenCV axes (x right, y down, z forward)."""
    zc = target - eye
    zc = zc / np.linalg.norm(zc)
    xc = np.cross(down, zc)
    xc = xc / np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    rot = np.stack([xc, yc, zc])
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, -rot @ eye
    return out


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _matrix_to_wxyz(m: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] → unit quaternions [..., 4] (w first)."""
    w = np.sqrt(np.clip(1 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2], 1e-12, None)) / 2
    x = (m[..., 2, 1] - m[..., 1, 2]) / (4 * w)
    y = (m[..., 0, 2] - m[..., 2, 0]) / (4 * w)
    z = (m[..., 1, 0] - m[..., 0, 1]) / (4 * w)
    q = np.stack([w, x, y, z], -1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _texture(rng: np.random.Generator, uv: np.ndarray) -> np.ndarray:
    """Colours [K, 3] for surface coordinates uv [K, 2] in [0, 1]: a random mix of checks, stripes
    and smooth noise on a random palette, so photometric losses have edges to hold on to."""
    palette = rng.uniform(0.05, 0.95, (3, 3))
    kind = rng.integers(3)
    freq = rng.uniform(3, 9)
    if kind == 0:
        pattern = ((np.floor(uv[:, 0] * freq) + np.floor(uv[:, 1] * freq)) % 2)[:, None]
    elif kind == 1:
        pattern = (0.5 + 0.5 * np.sin(2 * np.pi * freq * (uv @ rng.normal(size=2))))[:, None]
    else:
        phases = rng.uniform(0, 2 * np.pi, 4)
        pattern = (0.5 + 0.25 * (np.sin(freq * uv[:, 0] * 3 + phases[0]) + np.sin(freq * uv[:, 1] * 2 + phases[1])))[:, None]
    noise = rng.normal(0, 0.03, (len(uv), 3))
    return np.clip(palette[0] * (1 - pattern) + palette[1] * pattern + noise, 0, 1)


@dataclass
class GaussianBlock:
    """Gaussians in a local frame; `pose(t)` places them in the world."""

    means: np.ndarray
    scales: np.ndarray
    rotations: np.ndarray  # [K, 3, 3]
    opacities: np.ndarray
    colors: np.ndarray


@dataclass
class MovingObject:
    block: GaussianBlock
    centre: np.ndarray
    path_amplitude: np.ndarray  # [3, 3]: per axis, per harmonic
    path_frequency: np.ndarray  # [3]
    path_phase: np.ndarray  # [3, 3]
    spin_axis: np.ndarray
    spin_rate: float
    deform: float  # 0: rigid; otherwise the amplitude of a squash-and-stretch along local y
    deform_rate: float
    # World 2: how the centre moves ("harmonic": the path above; "ballistic", "pivot",
    # "stopgo": `motion_params`), and a joint the object bends at (None: rigid).
    motion: str = "harmonic"
    motion_params: dict = field(default_factory=dict)
    joint: dict | None = None

    def _centre(self, t: float) -> np.ndarray:
        p = self.motion_params
        if self.motion == "ballistic":
            # Thrown, falling under gravity (world y points down) onto the floor, bouncing with
            # 60% of its speed; horizontal drift at constant speed.
            g, floor = 5.0, p["floor"]
            tau, y, v = t, float(self.centre[1]), float(p["vy"])
            for _ in range(32):
                hit = (-v + np.sqrt(v * v + 2 * g * max(floor - y, 0.0))) / g
                if hit >= tau or hit <= 1e-6:
                    break
                tau, y, v = tau - hit, floor, -0.6 * (v + g * hit)
            y = min(y + v * tau + 0.5 * g * tau * tau, floor)
            return self.centre + np.array([p["vx"] * t, y - self.centre[1], p["vz"] * t])
        if self.motion == "pivot":
            # Swept round an axis through a point beside it.
            return p["pivot"] + _axis_angle(p["axis"], p["rate"] * t) @ (self.centre - p["pivot"])
        if self.motion == "stopgo":
            # Eased legs between waypoints, each followed by a pause.
            legs, per = p["waypoints"], p["leg"]
            k = min(int(t // per), len(legs) - 2)
            u = min(max((t - k * per) / (0.6 * per), 0.0), 1.0)
            u = u * u * (3 - 2 * u)
            return legs[k] * (1 - u) + legs[k + 1] * u
        harmonics = np.sin(self.path_frequency[None, :] * t * np.arange(1, 4)[:, None] + self.path_phase)
        return self.centre + (self.path_amplitude * harmonics).sum(axis=0)

    def transform(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rotation [3, 3], translation [3], per-axis local stretch [3]) at time t."""
        stretch = np.ones(3)
        if self.deform:
            s = 1 + self.deform * np.sin(self.deform_rate * t)
            stretch = np.array([1 / np.sqrt(s), s, 1 / np.sqrt(s)])
        return _axis_angle(self.spin_axis, self.spin_rate * t), self._centre(t), stretch

    def _bent(self, local: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Local points past the joint turned about it at time t: (points, the turn, which)."""
        if self.joint is None:
            return local, None, np.zeros(len(local), bool)
        j = self.joint
        beyond = (local - j["pivot"]) @ j["along"] > 0
        turn = _axis_angle(j["axis"], j["amplitude"] * np.sin(j["rate"] * t + j["phase"]))
        out = local.copy()
        out[beyond] = (local[beyond] - j["pivot"]) @ turn.T + j["pivot"]
        return out, turn, beyond

    def gaussians(self, t: float) -> GaussianBlock:
        rot, trans, stretch = self.transform(t)
        b = self.block
        local, turn, beyond = self._bent(b.means, t)
        rotations = b.rotations
        if turn is not None:
            rotations = rotations.copy()
            rotations[beyond] = turn @ rotations[beyond]
        local = local * stretch
        return GaussianBlock(
            local @ rot.T + trans, b.scales * stretch, rot @ rotations, b.opacities, b.colors
        )

    def points(self, local: np.ndarray, t: float) -> np.ndarray:
        rot, trans, stretch = self.transform(t)
        return (self._bent(local, t)[0] * stretch) @ rot.T + trans


@dataclass
class Scene:
    seed: int
    background: GaussianBlock
    objects: list[MovingObject]
    camera_motion: str
    duration: float
    fps: float
    normalised_intrinsics: tuple[float, float, float, float]
    camera_path: dict = field(default_factory=dict)
    track_points: list[np.ndarray] = field(default_factory=list)  # per object, local points [K, 3]
    light: tuple[float, float] = (1.0, 1.0)  # colour gain at the start and the end (world 2)

    def camera(self, t: float) -> np.ndarray:
        """World-to-camera [4, 4] at time t."""
        p = self.camera_path
        s = t / self.duration
        if self.camera_motion == "orbit":
            angle = p["angle0"] + p["sweep"] * s
            eye = p["centre"] + p["radius"] * np.array([np.sin(angle), -p["height"], -np.cos(angle)])
            return _look_at(eye, p["centre"])
        if self.camera_motion == "pan":
            yaw = p["sweep"] * (s - 0.5)
            direction = np.array([np.sin(yaw), 0.0, np.cos(yaw)])
            return _look_at(p["eye"], p["eye"] + direction)
        if self.camera_motion == "dolly":
            eye = p["eye"] + p["travel"] * s * p["direction"]
            return _look_at(eye, eye + p["direction"])
        if self.camera_motion == "handheld":
            # A slow turn with the hand's shake on the position and the aim.
            shake = sum(a * np.sin(f * t + ph) for a, f, ph in p["shake"])
            yaw = p["sweep"] * (s - 0.5)
            direction = np.array([np.sin(yaw), 0.05, np.cos(yaw)])
            return _look_at(p["eye"] + shake, p["eye"] + shake + direction + 2 * shake)
        return _look_at(p["eye"], p["eye"] + p["direction"])

    def gaussians(self, t: float) -> GaussianBlock:
        blocks = [self.background] + [o.gaussians(t) for o in self.objects]
        out = GaussianBlock(*(np.concatenate([getattr(b, f) for b in blocks]) for f in ("means", "scales", "rotations", "opacities", "colors")))
        if self.light != (1.0, 1.0):
            gain = self.light[0] + (self.light[1] - self.light[0]) * t / self.duration
            out.colors = np.clip(out.colors * gain, 0, 1)
        return out

    def dynamic_flags(self) -> np.ndarray:
        """True for the Gaussians of moving objects, in the order of `gaussians(t)`."""
        counts = [len(self.background.opacities)] + [len(o.block.opacities) for o in self.objects]
        return np.concatenate([np.full(c, i > 0) for i, c in enumerate(counts)])

    def object_ids(self) -> np.ndarray:
        """Each Gaussian's object id, in the order of `gaussians(t)`: 0 for the room, k for the k-th
        object (ids are per scene: object 1 of one clip has nothing to do with object 1 of another)."""
        counts = [len(self.background.opacities)] + [len(o.block.opacities) for o in self.objects]
        return np.concatenate([np.full(c, i, dtype=np.int64) for i, c in enumerate(counts)])

    def tracks_3d(self, t: float) -> np.ndarray:
        """World positions [K, 3] of the tracked object points at time t."""
        if not self.objects:
            return np.zeros((0, 3))
        return np.concatenate([o.points(p, t) for o, p in zip(self.objects, self.track_points)])


# scikit-image's sample photographs released under CC0 (their docstrings say so), shipped in its
# wheel: textures from the real world for world 2.
PHOTOS = ("coffee", "chelsea", "brick", "grass", "gravel")


def _photo_texture(rng: np.random.Generator, uv: np.ndarray) -> np.ndarray:
    """Colours [K, 3] at uv [K, 2] from a random window of a random photograph (a grey one
    tinted)."""
    from skimage import data

    image = getattr(data, PHOTOS[int(rng.integers(len(PHOTOS)))])().astype(np.float64) / 255.0
    if image.ndim == 2:
        image = image[..., None] * rng.uniform(0.4, 1.0, 3)
    h, w = image.shape[:2]
    span = rng.uniform(0.2, 0.9)
    x0, y0 = rng.uniform(0, 1 - span, 2)
    cols = np.clip(((x0 + span * uv[:, 0]) * (w - 1)).astype(int), 0, w - 1)
    rows = np.clip(((y0 + span * uv[:, 1]) * (h - 1)).astype(int), 0, h - 1)
    return image[rows, cols]


def _noise_texture(rng: np.random.Generator, uv: np.ndarray) -> np.ndarray:
    """Colours [K, 3] at uv [K, 2]: value noise summed over 2-4 octaves from a random base scale,
    between two random colours."""
    total, weight = np.zeros(len(uv)), 0.0
    base = rng.uniform(2, 12)
    for octave in range(int(rng.integers(2, 5))):
        lattice = rng.uniform(0, 1, (32, 32))
        p = uv * base * 2**octave
        i, f = np.floor(p).astype(int) % 32, p - np.floor(p)
        a, b = lattice[i[:, 0], i[:, 1]], lattice[(i[:, 0] + 1) % 32, i[:, 1]]
        c, d = lattice[i[:, 0], (i[:, 1] + 1) % 32], lattice[(i[:, 0] + 1) % 32, (i[:, 1] + 1) % 32]
        value = (a * (1 - f[:, 0]) + b * f[:, 0]) * (1 - f[:, 1]) + (c * (1 - f[:, 0]) + d * f[:, 0]) * f[:, 1]
        total += value * 0.5**octave
        weight += 0.5**octave
    mix = (total / weight)[:, None]
    low, high = rng.uniform(0.05, 0.95, (2, 3))
    return low * (1 - mix) + high * mix


def _texture_world2(rng: np.random.Generator, uv: np.ndarray) -> np.ndarray:
    """World 2's textures: world 1's patterns, multi-scale noise or a photograph."""
    kind = int(rng.integers(3))
    return (_texture, _noise_texture, _photo_texture)[kind](rng, uv)


def _surface(rng, origin, u_axis, v_axis, size_u, size_v, spacing, texture=_texture) -> GaussianBlock:
    nu, nv = max(2, int(size_u / spacing)), max(2, int(size_v / spacing))
    uu, vv = np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij")
    uv = np.stack([uu.ravel(), vv.ravel()], -1)
    uv_jitter = uv + rng.uniform(-0.25, 0.25, uv.shape) / np.array([nu, nv])
    means = origin + uv_jitter[:, :1] * size_u * u_axis + uv_jitter[:, 1:] * size_v * v_axis
    normal = np.cross(u_axis, v_axis)
    frame = np.stack([u_axis, v_axis, normal], axis=1)  # columns: local x, y, z
    k = len(means)
    return GaussianBlock(
        means,
        np.tile([0.7 * size_u / nu, 0.7 * size_v / nv, 0.002], (k, 1)),
        np.repeat(frame[None], k, axis=0),
        np.full(k, 0.95),
        texture(rng, uv),
    )


def _room(rng, gaussian_budget: int, texture=_texture) -> GaussianBlock:
    width, depth, height = rng.uniform(4, 7), rng.uniform(5, 8), rng.uniform(2.5, 3.5)
    floor_y, front_z = 1.2, -1.0
    x0, z1 = -width / 2, front_z + depth
    ex, ey, ez = np.eye(3)
    walls = [  # (origin, u axis, v axis, size u, size v)
        (np.array([x0, floor_y, front_z]), ex, ez, width, depth),  # floor
        (np.array([x0, floor_y - height, z1]), ex, ey, width, height),  # back wall
        (np.array([x0, floor_y - height, front_z]), ez, ey, depth, height),  # left wall
        (np.array([-x0, floor_y - height, front_z]), ez, ey, depth, height),  # right wall
        (np.array([x0, floor_y - height, front_z]), ex, ez, width, depth),  # ceiling
        (np.array([x0, floor_y - height, front_z]), ex, ey, width, height),  # front wall (behind the cameras)
    ]
    area = sum(su * sv for _, _, _, su, sv in walls)
    spacing = np.sqrt(area / gaussian_budget)
    blocks = [_surface(rng, *w, spacing, texture=texture) for w in walls]
    return GaussianBlock(*(np.concatenate([getattr(b, f) for b in blocks]) for f in ("means", "scales", "rotations", "opacities", "colors")))


def _object(rng, count: int, radii: np.ndarray | None = None, texture=_texture) -> tuple[GaussianBlock, np.ndarray]:
    """A textured ellipsoid or box of `count` Gaussians (half-axes `radii`, random when not
    given), and a few surface points to track."""
    radii = rng.uniform(0.15, 0.45, 3) if radii is None else radii
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    if rng.random() < 0.5:
        surface = directions * radii
    else:
        surface = directions / np.abs(directions).max(axis=1, keepdims=True) * radii
    uv = np.stack([np.arctan2(directions[:, 0], directions[:, 2]) / (2 * np.pi) + 0.5, directions[:, 1] * 0.5 + 0.5], -1)
    rots = np.stack([_axis_angle(rng.normal(size=3), rng.uniform(0, np.pi)) for _ in range(count)])
    size = np.sqrt(4 * np.pi * radii.mean() ** 2 / count)
    block = GaussianBlock(surface, np.tile([size, size, size * 0.4], (count, 1)) * rng.uniform(0.8, 1.2, (count, 1)), rots, np.full(count, 0.9), texture(rng, uv))
    return block, surface[rng.choice(count, size=min(8, count), replace=False)]


def make_scene(seed: int, duration: float = (FRAMES - 1) / FPS, fps: float = FPS, gaussians: int = 1800, world: int = 1) -> Scene:
    """The scene of `seed` in `world` (1 or 2): the same seed always gives the same scene."""
    if world == 2:
        return _make_scene_world2(seed, duration, fps, gaussians)
    if world != 1:
        raise ValueError(f"no world {world} (1 or 2)")
    rng = np.random.default_rng(seed)
    n_objects = int(rng.integers(1, 5))
    per_object = int(rng.integers(60, 160))
    background = _room(rng, max(200, gaussians - n_objects * per_object))
    objects, tracks = [], []
    for _ in range(n_objects):
        block, track = _object(rng, per_object)
        centre = np.array([rng.uniform(-1.2, 1.2), rng.uniform(0.0, 0.8), rng.uniform(1.8, 3.5)])
        deform = float(rng.uniform(0.1, 0.35)) if rng.random() < 0.3 else 0.0
        objects.append(
            MovingObject(
                block, centre, rng.uniform(-0.25, 0.25, (3, 3)) / np.arange(1, 4)[:, None], rng.uniform(0.5, 2.0, 3),
                rng.uniform(0, 2 * np.pi, (3, 3)), rng.normal(size=3), float(rng.uniform(-2, 2)), deform, float(rng.uniform(2, 6)),
            )  # fmt: skip
        )
        tracks.append(track)
    motion = CAMERA_MOTIONS[int(rng.integers(len(CAMERA_MOTIONS)))]
    look = np.array([0.0, 0.3, 2.6])
    path = {
        "orbit": {"centre": look, "radius": rng.uniform(2.2, 3.0), "height": rng.uniform(0.0, 0.2), "angle0": rng.uniform(-0.3, 0.3), "sweep": rng.uniform(0.5, 0.9) * rng.choice([-1, 1])},
        "pan": {"eye": np.array([0.0, 0.0, -0.3]), "sweep": rng.uniform(0.3, 0.6) * rng.choice([-1, 1])},
        "dolly": {"eye": np.array([0.0, 0.0, -0.5]), "direction": np.array([rng.uniform(-0.2, 0.2), 0.05, 1.0]), "travel": rng.uniform(1.2, 2.0)},
        "static": {"eye": np.array([0.0, 0.0, -0.3]), "direction": np.array([rng.uniform(-0.2, 0.2), 0.05, 1.0])},
    }[motion]
    if "direction" in path:
        path["direction"] = path["direction"] / np.linalg.norm(path["direction"])
    return Scene(seed, background, objects, motion, duration, fps, (C4G_FOCAL, C4G_FOCAL, 0.5, 0.5), path, tracks)


# World 2's families and motions.
FAMILIES_WORLD2 = ("solid", "stick", "card", "jointed", "squashy")
MOTIONS_WORLD2 = ("harmonic", "ballistic", "pivot", "stopgo")
CAMERA_MOTIONS_WORLD2 = CAMERA_MOTIONS + ("handheld",)


def _object_world2(rng: np.random.Generator, count: int, family: str) -> tuple[GaussianBlock, np.ndarray, dict | None, float]:
    """An object of `family`: its Gaussians, points to track, its joint (jointed) and how much
    it squashes (squashy)."""
    radii = {
        "solid": rng.uniform(0.15, 0.45, 3),
        "stick": np.array([0.03, rng.uniform(0.3, 0.6), 0.03]),
        "card": np.array([rng.uniform(0.25, 0.45), rng.uniform(0.25, 0.45), 0.015]),
        "jointed": np.array([0.08, rng.uniform(0.4, 0.6), 0.08]),
        "squashy": rng.uniform(0.2, 0.4, 3),
    }[family]
    block, track = _object(rng, count, radii, texture=_texture_world2)
    joint = None
    if family == "jointed":
        axis = np.array([rng.normal(), 0.0, rng.normal()])
        joint = {
            "pivot": np.zeros(3),
            "along": np.array([0.0, -1.0, 0.0]),
            "axis": axis / np.linalg.norm(axis),
            "amplitude": float(rng.uniform(0.5, 1.2)),
            "rate": float(rng.uniform(2, 6)),
            "phase": float(rng.uniform(0, 2 * np.pi)),
        }
    deform = float(rng.uniform(0.2, 0.45)) if family == "squashy" else 0.0
    return block, track, joint, deform


def _make_scene_world2(seed: int, duration: float, fps: float, gaussians: int) -> Scene:
    rng = np.random.default_rng([2, seed])
    n_objects = int(rng.integers(1, 6))
    per_object = int(rng.integers(60, 160))
    background = _room(rng, max(200, gaussians - n_objects * per_object), texture=_texture_world2)
    objects, tracks = [], []
    for _ in range(n_objects):
        family = FAMILIES_WORLD2[int(rng.integers(len(FAMILIES_WORLD2)))]
        block, track, joint, deform = _object_world2(rng, per_object, family)
        centre = np.array([rng.uniform(-1.2, 1.2), rng.uniform(-0.2, 0.8), rng.uniform(1.8, 3.5)])
        motion = MOTIONS_WORLD2[int(rng.integers(len(MOTIONS_WORLD2)))]
        extent = float(np.abs(block.means).max())
        params: dict = {}
        if motion == "ballistic":
            params = {"floor": 1.2 - extent, "vy": float(rng.uniform(-2.5, -0.5)), "vx": float(rng.uniform(-0.8, 0.8)), "vz": float(rng.uniform(-0.4, 0.4))}
        elif motion == "pivot":
            axis = rng.normal(size=3)
            params = {"pivot": centre + rng.normal(size=3) * np.array([0.5, 0.2, 0.5]), "axis": axis / np.linalg.norm(axis), "rate": float(rng.uniform(0.6, 1.8) * rng.choice([-1, 1]))}
        elif motion == "stopgo":
            params = {"waypoints": [centre] + [centre + rng.normal(size=3) * np.array([0.5, 0.15, 0.4]) for _ in range(3)], "leg": duration / 3}
        objects.append(
            MovingObject(
                block, centre, rng.uniform(-0.25, 0.25, (3, 3)) / np.arange(1, 4)[:, None], rng.uniform(0.5, 2.0, 3),
                rng.uniform(0, 2 * np.pi, (3, 3)), rng.normal(size=3), float(rng.uniform(-2, 2)), deform, float(rng.uniform(2, 6)),
                motion, params, joint,
            )  # fmt: skip
        )
        tracks.append(track)
    motion = CAMERA_MOTIONS_WORLD2[int(rng.integers(len(CAMERA_MOTIONS_WORLD2)))]
    look = np.array([0.0, 0.3, 2.6])
    path = {
        "orbit": {"centre": look, "radius": rng.uniform(2.0, 3.2), "height": rng.uniform(-0.1, 0.3), "angle0": rng.uniform(-0.4, 0.4), "sweep": rng.uniform(0.3, 1.0) * rng.choice([-1, 1])},
        "pan": {"eye": np.array([0.0, 0.0, -0.3]), "sweep": rng.uniform(0.2, 0.7) * rng.choice([-1, 1])},
        "dolly": {"eye": np.array([0.0, 0.0, -0.5]), "direction": np.array([rng.uniform(-0.25, 0.25), 0.05, 1.0]), "travel": rng.uniform(0.8, 2.2)},
        "static": {"eye": np.array([0.0, 0.0, -0.3]), "direction": np.array([rng.uniform(-0.25, 0.25), 0.05, 1.0])},
        "handheld": {"eye": np.array([0.0, 0.0, -0.3]), "sweep": rng.uniform(-0.3, 0.3), "shake": [(rng.normal(size=3) * 0.012, rng.uniform(12, 35), rng.uniform(0, 2 * np.pi)) for _ in range(3)]},
    }[motion]
    if "direction" in path:
        path["direction"] = path["direction"] / np.linalg.norm(path["direction"])
    light = (float(rng.uniform(0.75, 1.1)), float(rng.uniform(0.9, 1.25))) if rng.random() < 0.5 else (1.0, 1.0)
    return Scene(seed, background, objects, motion, duration, fps, (C4G_FOCAL, C4G_FOCAL, 0.5, 0.5), path, tracks, light)


def normalise_to_first_camera(w2c: np.ndarray, first: int, last: int, median_depth_first: float) -> tuple[np.ndarray, float]:
    """The model's frame for a set of context cameras: camera `first` becomes the identity, and
    world units are scaled so the distance between the `first` and `last` context cameras is 1.

    When the camera does not move (baseline below MIN_BASELINE) there is no baseline to use; the
    scale then makes the median depth of the first frame STATIC_MEDIAN_DEPTH instead.

    Returns (world-to-camera matrices in the new frame [T, 4, 4], scale: new units per old unit)."""
    to_first = np.linalg.inv(w2c[first])  # old camera-first → old world
    rebased = w2c @ to_first  # new world = camera `first`'s frame, old units
    centres = -np.einsum("tij,tj->ti", np.transpose(rebased[:, :3, :3], (0, 2, 1)), rebased[:, :3, 3])
    baseline = np.linalg.norm(centres[last] - centres[first])
    scale = 1.0 / baseline if baseline > MIN_BASELINE else STATIC_MEDIAN_DEPTH / median_depth_first
    out = rebased.copy()
    out[:, :3, 3] *= scale
    return out, scale


@dataclass
class RenderedClip:
    times: np.ndarray  # [T] seconds
    frames: np.ndarray  # [T, H, W, 3] in [0, 1]
    depth: np.ndarray  # [T, H, W] expected depth
    alpha: np.ndarray  # [T, H, W]
    dynamic_mask: np.ndarray  # [T, H, W] True where moving objects carry most of the pixel
    world_to_camera: np.ndarray  # [T, 4, 4]
    intrinsics: np.ndarray  # [4] fx, fy, cx, cy in pixels
    tracks_3d: np.ndarray  # [T, K, 3] world
    tracks_2d: np.ndarray  # [T, K, 2] pixels
    tracks_visible: np.ndarray  # [T, K] in front of the camera, inside the image and not occluded


def render_clip(scene: Scene, times: np.ndarray, size: int, cameras: np.ndarray | None = None) -> RenderedClip:
    """Renders the scene at `times` (from the scene's own camera path unless `cameras` [T, 4, 4]
    gives other world-to-camera poses: novel views), all frames in one batch."""
    fx, fy, cx, cy = (v * size for v in scene.normalised_intrinsics)
    w2c = np.stack([scene.camera(float(t)) if cameras is None else cameras[i] for i, t in enumerate(times)])
    sets = [scene.gaussians(float(t)) for t in times]
    f64 = lambda key: torch.from_numpy(np.stack([getattr(g, key) for g in sets]))  # noqa: E731
    rots = torch.from_numpy(np.stack([_matrix_to_wxyz(g.rotations) for g in sets]))
    flags = torch.from_numpy(np.broadcast_to(scene.dynamic_flags()[None, :, None], (len(times), len(sets[0].opacities), 3)).astype(np.float64))
    args = (f64("means"), f64("scales"), rots, f64("opacities"))
    with torch.no_grad():
        r = render_batch(*args, f64("colors"), (fx, fy, cx, cy), torch.from_numpy(w2c), size, size)
        dyn = render_batch(*args, flags, (fx, fy, cx, cy), torch.from_numpy(w2c), size, size)["rgb"][..., 0]
    depth = r["expected_depth"].numpy()
    pts = np.stack([scene.tracks_3d(float(t)) for t in times])  # [T, K, 3]
    cam = np.einsum("tij,tkj->tki", w2c[:, :3, :3], pts) + w2c[:, None, :3, 3]
    z = np.maximum(cam[..., 2], 1e-9)
    uv = np.stack([fx * cam[..., 0] / z + cx, fy * cam[..., 1] / z + cy], -1)
    inside = (cam[..., 2] > 0.01) & (uv >= 0).all(-1) & (uv < size).all(-1)
    px = np.clip(uv.astype(int), 0, size - 1)
    surface = np.take_along_axis(depth.reshape(len(times), -1), px[..., 1] * size + px[..., 0], axis=1)
    visible = inside & (cam[..., 2] <= surface * 1.05 + 0.02)
    return RenderedClip(
        np.asarray(times, dtype=np.float64), r["rgb"].clamp(0, 1).numpy().astype(np.float32), depth.astype(np.float32),
        r["alpha"].numpy().astype(np.float32), dyn.numpy() > 0.5, w2c, np.array([fx, fy, cx, cy]), pts, uv, visible,
    )  # fmt: skip


# Object ids a render can tell apart: the room and up to 7 objects (world 1 has at most 4, world 2 5).
OBJECT_IDS = 8


def render_object_ids(scene: Scene, times: np.ndarray, size: int, cameras: np.ndarray | None = None) -> np.ndarray:
    """The object id [T, H, W] (uint8, `Scene.object_ids`) that carries most of each pixel's
    weight, rendered like `render_clip` (same cameras, same Gaussians) but separately from it, so
    that the clips it makes stay exactly as they were."""
    ids = scene.object_ids()
    if ids.max() >= OBJECT_IDS:
        raise ValueError(f"scene {scene.seed} has {ids.max()} objects; object-id renders tell {OBJECT_IDS - 1} apart")
    intrinsics = tuple(v * size for v in scene.normalised_intrinsics)
    w2c = np.stack([scene.camera(float(t)) if cameras is None else cameras[i] for i, t in enumerate(times)])
    sets = [scene.gaussians(float(t)) for t in times]
    stack = lambda key: np.stack([getattr(g, key) for g in sets])  # noqa: E731
    rots = np.stack([_matrix_to_wxyz(g.rotations) for g in sets])
    return dominant_ids((stack("means"), stack("scales"), rots, stack("opacities")), ids, intrinsics, w2c, size)

