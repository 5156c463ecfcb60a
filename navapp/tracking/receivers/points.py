"""A data source's points, received: the receiver of every source whose features are in
``features.SOURCED`` and that has no module of its own here (the laparoscope).

Its points arrive as OpenIGTLink POINT messages whose device name is the feature's (pyigtl
0.3 decodes no POLYDATA). Untracked, they are in Reference already. Tracked (the config's
``[tools.<source>] pose``), they are in the tool's own frame — a tracked laparoscope's depth
points in its camera frame — and the tool's TRANSFORM (ToolToReference) places them: the
latest pose, if the watchdog's ``stale_s`` or less apart from the points on the sender's
clock; points without such a pose are refused, not placed where the tool was before.
"""

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ...features import TABLE
from ..config import TrackingConfig
from ..events import SourcePoints, ToolStatus, TransformSample
from .base import Event, Message, pose_matrix, seen


@dataclass
class PointsReceiver:
    source: str
    features: tuple[str, ...]  # its POINT devices: its features' names
    pose: str | None = None  # the tool's TRANSFORM placing its points (tracked), or None (in Reference)
    max_pose_age_s: float = 0.2  # points and pose at most this far apart (sender's clock)
    latest_pose: TransformSample | None = None

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
            p = self.latest_pose
            if p is None:
                raise ValueError(f"no {self.pose} yet to place the points")
            gap = abs(message.t_sent - p.t_sent)
            if gap > self.max_pose_age_s:
                raise ValueError(f"the last {self.pose} is {gap:.2f} s from the points "
                                 f"(more than {self.max_pose_age_s:g} s): not placed")
            pts = pts @ p.matrix[:3, :3].T + p.matrix[:3, 3]
        return SourcePoints(message.t, message.t_sent, message.device, pts)

    def keep(self, event: Event) -> None:
        if isinstance(event, TransformSample):
            self.latest_pose = event

    def fresh(self, status: Mapping[str, ToolStatus]) -> bool:
        return self.pose is None or seen(status, self.pose)


def make_points(source: str, config: TrackingConfig) -> PointsReceiver:
    """``source``'s points receiver, tracked when the config names its pose."""
    tool = config.tool(source)
    return PointsReceiver(source, tuple(f.name for f in TABLE if f.source == source),
                          None if tool is None else tool.pose, config.stale_s)
