"""The tracked ultrasound probe, received: its pose (TRANSFORM ``ProbeToReference``) and its
frames (IMAGE ``Image_Reference``), each frame placed by its own embedded matrix or, with
``image_pose = "calibration"``, by the latest probe pose times ImageToProbe."""

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..config import TrackingConfig
from ..digitiser import Digitiser
from ..events import ProbePose, ProbeSample, ToolStatus, as_matrix
from .base import Event, Message, pose_matrix, seen


@dataclass
class ProbeReceiver:
    probe: str  # the probe's TRANSFORM (ProbeToReference)
    image: str  # the frames' IMAGE device
    image_pose: str  # "embedded" | "calibration" (``TrackingConfig.image_pose``)
    image_to_probe: np.ndarray  # (4, 4) pixel → mm, the calibration
    source: str = "ius"
    latest_pose: ProbePose | None = None
    latest_frame: ProbeSample | None = None

    @property
    def devices(self) -> tuple[str, ...]:
        return (self.probe, self.image)

    def takes(self, mtype: str, device: str) -> bool:
        return (mtype, device) in (("TRANSFORM", self.probe), ("IMAGE", self.image))

    def receive(self, message: Message) -> Event | None:
        if message.mtype == "TRANSFORM":
            return ProbePose(message.t, message.t_sent, pose_matrix(message))
        msg = message.body
        image = np.asarray(msg.image)  # an ImageMessage
        if image.ndim == 4:  # colour (k, j, i, components): luminance
            image = image[..., :3].mean(-1).astype(np.uint8) if image.shape[-1] >= 3 else image[..., 0]
        if image.ndim == 3:
            if image.shape[0] != 1:
                raise ValueError(f"a volume of {image.shape[0]} slices, not an ultrasound frame")
            image = image[0]
        if image.ndim != 2 or image.size == 0:
            raise ValueError(f"image of shape {msg.image.shape}")
        image = np.ascontiguousarray(image.astype(image.dtype.newbyteorder("=")))
        M = as_matrix(msg.ijk_to_world_matrix)
        if not np.isfinite(M).all():
            raise ValueError("image matrix not finite")
        if self.image_pose == "embedded":
            pose, source, age = M, "embedded", 0.0
        else:
            pp = self.latest_pose
            if pp is None:
                raise ValueError(f"no {self.probe} yet to place the image (image_pose = \"calibration\")")
            pose, source = pp.probe_to_reference @ self.image_to_probe, "calibration"
            age = max(0.0, message.t_sent - pp.t_sent)
        spacing = (float(np.linalg.norm(pose[:3, 0])), float(np.linalg.norm(pose[:3, 1])))
        return ProbeSample(message.t, message.t_sent, pose, image, spacing, source, age)

    def keep(self, event: Event) -> None:
        if isinstance(event, ProbePose):
            self.latest_pose = event
        elif isinstance(event, ProbeSample):
            self.latest_frame = event

    def fresh(self, status: Mapping[str, ToolStatus]) -> bool:
        """The frame's streams are seen: the image, and the probe's pose when it places it."""
        streams = [self.image] + ([self.probe] if self.image_pose == "calibration" else [])
        return all(seen(status, d) for d in streams)


def make(config: TrackingConfig, digitiser: Digitiser) -> ProbeReceiver:
    return ProbeReceiver(config.probe, config.image, config.image_pose, config.image_to_probe)
