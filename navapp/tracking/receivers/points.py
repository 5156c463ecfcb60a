"""A data source's points, received: the receiver of every source whose features are in
``features.SOURCED`` and that has no module of its own here (the laparoscope).

Its points arrive as OpenIGTLink POINT messages whose device name is the feature's (pyigtl
0.3 decodes no POLYDATA). Untracked, they are in Reference already. Tracked (the config's
``[tools.<source>] pose``), they are in the tool's own frame — a tracked laparoscope's depth
points in its camera frame — and the tool's TRANSFORM (ToolToReference) places them at the
points' own time (their OpenIGTLink timestamp, the sender's clock): the pose interpolated
between the two kept poses around it (slerp), as PLUS places a tracked frame; a depth
matcher sends its points some tens of ms after the images it matched, by when the camera
has moved on. Both poses must be the watchdog's ``stale_s`` or less from the points (a gap
in the stream, the tool out of view, is not bridged); points newer or older than every kept
pose take the nearest one if it is that close. Others are refused: never placed where the
tool was a while before.

Its settings: ``[tools.<source>] pose`` in the tracking TOML file, one table per tracked
source (without one its points arrive in Reference).
"""

from bisect import bisect_left
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ...errors import InputError
from ...features import SOURCED, TABLE
from ...geometry.transforms import apply, interpolate_pose
from ..events import SourcePoints, ToolStatus, TransformSample
from .base import Event, Message, Shared, device_name, pose_matrix, seen, typed

POSES_KEPT = 256  # ~2.5 s of a 100 Hz tracker: a depth matcher's points are far younger
KEYS: dict[str, dict[str, type]] = {}
TABLES = ("tools",)  # ``[tools.<source>]``: read whole here
_TOOL_KEYS: dict[str, type] = {"pose": str}
TRACKABLE = tuple(dict.fromkeys(f.source for f in TABLE if f.name in SOURCED))  # sources sending POINT messages


@dataclass(frozen=True)
class PointsSettings:
    """A source's points' settings: ``pose``, the TRANSFORM (ToolToReference, mm) placing its
    POINT messages, which then arrive in the tool's own frame (a tracked laparoscope's camera
    frame); None: they arrive in Reference."""

    source: str  # a ``features.TABLE`` source with features in ``features.SOURCED``
    pose: str | None = None

    @property
    def named(self) -> tuple[tuple[str, str], ...]:
        return () if self.pose is None else ((f"tools.{self.source}.pose", self.pose),)


@dataclass
class PointsReceiver:
    source: str
    features: tuple[str, ...]  # its POINT devices: its features' names
    pose: str | None = None  # the tool's TRANSFORM placing its points (tracked), or None (in Reference)
    max_pose_age_s: float = 0.2  # points and the nearest pose at most this far apart (sender's clock)
    poses: deque[TransformSample] = field(default_factory=lambda: deque(maxlen=POSES_KEPT))  # in time order

    @property
    def latest_pose(self) -> TransformSample | None:
        return self.poses[-1] if self.poses else None

    @property
    def devices(self) -> tuple[str, ...]:
        return () if self.pose is None else (self.pose,)

    def takes(self, mtype: str, device: str) -> bool:
        return (mtype == "POINT" and device in self.features) or (mtype == "TRANSFORM" and device == self.pose)

    def receive(self, message: Message) -> Event | None:
        if message.mtype == "TRANSFORM":
            return TransformSample(message.t, message.t_sent, message.device, pose_matrix(message))
        pts = np.asarray(message.body.positions, float).reshape(-1, 3)
        if not np.isfinite(pts).all():
            raise ValueError("points not finite")
        if self.pose is not None:
            pts = apply(self.pose_at(message.t_sent), pts)
        return SourcePoints(message.t, message.t_sent, message.device, pts)

    def pose_at(self, t: float) -> np.ndarray:
        """ToolToReference (4, 4) at ``t`` (the sender's clock), or ``ValueError`` saying why not."""
        if not self.poses:
            raise ValueError(f"no {self.pose} yet to place the points")
        times = [p.t_sent for p in self.poses]
        i = bisect_left(times, t)
        if i < len(times) and times[i] == t:
            return self.poses[i].matrix
        if 0 < i < len(times):
            a, b = self.poses[i - 1], self.poses[i]
            gap = max(t - a.t_sent, b.t_sent - t)
            if gap > self.max_pose_age_s:  # the tool went untracked (PLUS's invalid poses are dropped)
                raise ValueError(f"no {self.pose} within {self.max_pose_age_s:g} s on each side of the points "
                                 f"(poses {a.t_sent - t:+.2f} s and {b.t_sent - t:+.2f} s from them): not placed")
            return interpolate_pose(a.matrix, b.matrix, (t - a.t_sent) / (b.t_sent - a.t_sent))
        nearest = self.poses[min(i, len(times) - 1)]
        gap = abs(t - nearest.t_sent)
        if gap > self.max_pose_age_s:
            side = "last" if i == len(times) else "first kept"
            raise ValueError(f"the {side} {self.pose} is {gap:.2f} s from the points "
                             f"(more than {self.max_pose_age_s:g} s): not placed")
        return nearest.matrix

    def keep(self, event: Event) -> None:
        if isinstance(event, TransformSample):
            self.poses.append(event)  # the client keeps each device's messages in time order

    def fresh(self, status: Mapping[str, ToolStatus]) -> bool:
        return self.pose is None or seen(status, self.pose)


def default(source: str) -> PointsSettings:
    return PointsSettings(source)


def parse(source: str, data: Mapping, path=None) -> PointsSettings:
    """``source``'s settings from the TOML file's ``data``: its ``[tools.<source>]`` table,
    every table of ``[tools]`` checked (a tool no source sends points for is refused)."""
    tools = data.get("tools", {})
    for name, keys in tools.items():
        if name not in TRACKABLE:
            raise InputError(f"unknown tool [tools.{name}] (known: {', '.join(TRACKABLE) or 'none'})", path)
        if not isinstance(keys, dict):
            raise InputError(f"[tools.{name}] must be a table", path)
        for key, value in keys.items():
            if key not in _TOOL_KEYS:
                raise InputError(f"unknown key tools.{name}.{key} (known: {', '.join(_TOOL_KEYS)})", path)
            typed(value, _TOOL_KEYS[key], f"tools.{name}.{key}", path)
        if "pose" not in keys:
            raise InputError(f"tools.{name}.pose is missing (the TRANSFORM that places its points)", path)
    if source not in tools:
        return PointsSettings(source)
    return PointsSettings(source, device_name(tools[source]["pose"], f"tools.{source}.pose", path))


def make(settings: PointsSettings, shared: Shared) -> PointsReceiver:
    """``settings.source``'s points receiver, tracked when its settings name its pose."""
    return PointsReceiver(settings.source, tuple(f.name for f in TABLE if f.source == settings.source),
                          settings.pose, shared.stale_s)
