"""The speed/accuracy options every decoding request takes: a :data:`Quality` preset,
:class:`Keyframes` and :class:`Prune` (``docs/api.md``: Quality, Keyframes, Pruning), and the
:data:`Scene` that serves it (``docs/api.md``: Fitting).

They are passed through to the server as they are: the server owns their meaning, validates
them and answers a bad one with ``invalid_input`` saying what to change. This module only gives
them types and turns them into the REST JSON and the gRPC messages.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Literal, Mapping, Optional, Union

#: A named point of the trade: ``exact`` (default), ``balanced``, ``fast``.
Quality = Literal["exact", "balanced", "fast"]

#: Which scene serves a request: ``auto`` (the server's default: the clip's fitted scene when it
#: has one and the request asks for no approximation and no features), ``feed-forward`` (the
#: model's answer) or ``fitted`` (what :meth:`Client.fit <c4g_client.Client.fit>` made).
Scene = Literal["auto", "feed-forward", "fitted"]

#: The header an answer names the scene that served it in (``feed-forward`` or ``fitted``).
SCENE_HEADER = "x-c4g-scene"


@dataclass(frozen=True)
class Keyframes:
    """Exact sets at keyframes, interpolated between them. Make one with :meth:`every`,
    :meth:`count` or :meth:`adaptive`."""

    every_s: Optional[float] = None
    count_: Optional[int] = None
    tolerance: Optional[float] = None
    color_tolerance: Optional[float] = None
    max: Optional[int] = None
    min_interval_s: Optional[float] = None

    @classmethod
    def every(cls, seconds: float) -> Keyframes:
        """A keyframe every ``seconds`` from the first requested time, and at the last."""
        return cls(every_s=seconds)

    @classmethod
    def count(cls, n: int) -> Keyframes:
        """``n`` keyframes spread evenly over the requested times (at least 2)."""
        return cls(count_=n)

    @classmethod
    def adaptive(
        cls,
        tolerance: float,
        *,
        color_tolerance: Optional[float] = None,
        max: Optional[int] = None,
        min_interval_s: Optional[float] = None,
    ) -> Keyframes:
        """Keyframes placed until interpolation is within ``tolerance`` (scene units) at the
        checks of every interval."""
        return cls(
            tolerance=tolerance,
            color_tolerance=color_tolerance,
            max=max,
            min_interval_s=min_interval_s,
        )

    def to_json(self) -> Dict[str, Any]:
        fields = {
            "every_s": self.every_s,
            "count": self.count_,
            "tolerance": self.tolerance,
            "color_tolerance": self.color_tolerance,
            "max": self.max,
            "min_interval_s": self.min_interval_s,
        }
        return {k: v for k, v in fields.items() if v is not None}


@dataclass(frozen=True)
class Prune:
    """Drop the Gaussians that change nothing visible (defaults: the server's, 0.5 px and
    1/255). `drop_queries=True` also drops their query tokens from the decoder itself: cheaper
    decodes, but the kept Gaussians change (queries attend to each other; docs/tradeoffs.md)."""

    contribution_px: Optional[float] = None
    opacity: Optional[float] = None
    drop_queries: Optional[bool] = None

    def to_json(self) -> Dict[str, Any]:
        fields = {
            "contribution_px": self.contribution_px,
            "opacity": self.opacity,
            "drop_queries": self.drop_queries,
        }
        return {k: v for k, v in fields.items() if v is not None}


KeyframesLike = Union[Keyframes, Mapping[str, Any]]
PruneLike = Union[Prune, Mapping[str, Any]]


def approximation_json(
    quality: Optional[str],
    keyframes: Optional[KeyframesLike],
    prune: Optional[PruneLike],
    scene: Optional[str] = None,
) -> Dict[str, Any]:
    """The request fields for the options given (none for those left out: server defaults)."""
    out: Dict[str, Any] = {}
    if scene is not None:
        out["scene"] = scene
    if quality is not None:
        out["quality"] = quality
    if keyframes is not None:
        out["keyframes"] = keyframes.to_json() if isinstance(keyframes, Keyframes) else dict(keyframes)
    if prune is not None:
        out["prune"] = prune.to_json() if isinstance(prune, Prune) else dict(prune)
    return out
