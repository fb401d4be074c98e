"""Cameras and camera paths, as the render and refine requests take them (``docs/api.md``,
Rendering).

A :class:`Camera` is a row-major 4×4 world-to-camera matrix in OpenCV axes (x right, y down,
z forward) of the scene frame (the first context camera's), and :class:`Intrinsics` as fractions
of the image size, so one camera renders at any resolution. The presets (:class:`Orbit`,
:class:`Spiral`, :class:`Dolly`) are paths the server builds around a camera. Plain dicts in the
API's JSON shape are accepted wherever these are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Sequence, Union

import numpy as np

#: The model's default focal length, as a fraction of the image size.
DEFAULT_FOCAL = 0.8767


@dataclass(frozen=True)
class Intrinsics:
    """Focal lengths and principal point as fractions of the image width (x) and height (y)."""

    fx: float = DEFAULT_FOCAL
    fy: float = DEFAULT_FOCAL
    cx: float = 0.5
    cy: float = 0.5

    def to_json(self) -> Dict[str, float]:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}

    def matrix(self, width: int, height: int) -> np.ndarray:
        """The 3×3 pixel matrix K at a resolution (what gsplat and OpenCV take)."""
        return np.array(
            [
                [self.fx * width, 0.0, self.cx * width],
                [0.0, self.fy * height, self.cy * height],
                [0.0, 0.0, 1.0],
            ]
        )


@dataclass(frozen=True)
class Camera:
    """A camera: ``world_to_camera`` (4×4, OpenCV axes; default the identity, the first
    context camera) and :class:`Intrinsics` (default the model's)."""

    world_to_camera: Optional[Any] = None
    intrinsics: Optional[Intrinsics] = None

    def view_matrix(self) -> np.ndarray:
        """The 4×4 world-to-camera matrix (the identity when none was given)."""
        if self.world_to_camera is None:
            return np.eye(4)
        m = np.asarray(self.world_to_camera, dtype=np.float64)
        return m.reshape(4, 4)

    def to_json(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {}
        if self.world_to_camera is not None:
            out["world_to_camera"] = [float(v) for v in self.view_matrix().reshape(-1)]
        if self.intrinsics is not None:
            out["intrinsics"] = self.intrinsics.to_json()
        return out

    @classmethod
    def from_json(cls, value: Mapping[str, Any]) -> Camera:
        intrinsics = value.get("intrinsics")
        return cls(
            value.get("world_to_camera"),
            Intrinsics(**intrinsics) if intrinsics else None,
        )


@dataclass(frozen=True)
class Orbit:
    """Cameras on an arc about a point ``depth`` ahead, sweeping ``angle_degrees``."""

    depth: float
    angle_degrees: float
    radius: Optional[float] = None

    def to_json(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {"kind": "orbit", "depth": self.depth, "angle_degrees": self.angle_degrees}
        if self.radius is not None:
            out["radius"] = self.radius
        return out


@dataclass(frozen=True)
class Spiral:
    """A spiral about the camera, looking at ``focus_depth``."""

    radii: Sequence[float]
    focus_depth: float
    rotations: float
    z_rate: float

    def to_json(self) -> Dict[str, Any]:
        return {
            "kind": "spiral",
            "radii": [float(r) for r in self.radii],
            "focus_depth": self.focus_depth,
            "rotations": self.rotations,
            "z_rate": self.z_rate,
        }


@dataclass(frozen=True)
class Dolly:
    """A move along the view axis; with ``subject_depth``, a dolly zoom."""

    distance: float
    subject_depth: Optional[float] = None

    def to_json(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {"kind": "dolly", "distance": self.distance}
        if self.subject_depth is not None:
            out["subject_depth"] = self.subject_depth
        return out


CameraLike = Union[Camera, Mapping[str, Any]]
TrajectoryLike = Union[Orbit, Spiral, Dolly, Mapping[str, Any]]


def camera_json(camera: Optional[CameraLike]) -> Optional[Dict[str, Any]]:
    """The API's JSON of a camera given as a :class:`Camera` or a dict."""
    if camera is None:
        return None
    if isinstance(camera, Camera):
        return camera.to_json()
    return dict(camera)


def as_camera(camera: Optional[CameraLike]) -> Camera:
    """A :class:`Camera` from either form (the default camera for ``None``)."""
    if camera is None:
        return Camera()
    if isinstance(camera, Camera):
        return camera
    return Camera.from_json(camera)


def trajectory_json(trajectory: Optional[TrajectoryLike]) -> Optional[Dict[str, Any]]:
    """The API's JSON of a preset given as a preset class or a dict."""
    if trajectory is None:
        return None
    if isinstance(trajectory, (Orbit, Spiral, Dolly)):
        return trajectory.to_json()
    return dict(trajectory)
