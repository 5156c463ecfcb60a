"""The tracked ultrasound probe, received: its pose (TRANSFORM ``ProbeToReference``) and its
frames (IMAGE ``Image_Reference``), each frame placed by its own embedded matrix or, with
``image_pose = "calibration"``, by the latest probe pose times ImageToProbe. Its settings:
``[devices] probe, image, image_pose`` and ``[calibration] image_to_probe`` in the tracking
TOML file."""

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ...errors import InputError
from ...simulation.probe import Probe
from ..events import ProbePose, ProbeSample, ToolStatus, as_matrix
from .base import Event, Message, Shared, device_name, pose_matrix, seen

KEYS: dict[str, dict[str, type]] = {  # its keys in the tracking TOML file
    "devices": {"probe": str, "image": str, "image_pose": str},
    "calibration": {"image_to_probe": list},
}
TABLES: tuple[str, ...] = ()
IMAGE_POSES = ("embedded", "calibration")


def full_image_matrix(m) -> np.ndarray:
    """An image-to-frame 4×4 whose third (slice) column is the image plane's normal at the
    column spacing. navapp's ``Probe.image_to_probe`` leaves that column degenerate (pixels
    have k = 0, so it never mattered); OpenIGTLink, PLUS and Slicer need it invertible."""
    m = np.array(m, float)
    n = np.cross(m[:3, 0], m[:3, 1])
    if np.linalg.norm(n) > 0:
        m[:3, 2] = n / np.linalg.norm(n) * np.linalg.norm(m[:3, 0])
    return m


def _default_image_to_probe():
    return full_image_matrix(Probe().image_to_probe())


@dataclass(frozen=True)
class ProbeSettings:
    """PLUS's names by default: a tracked probe ``ProbeToReference``; an image stream declared
    ``<Image Name="Image" EmbeddedTransformToFrame="Reference"/>`` arrives as ``Image_Reference``
    whose matrix already is ImageToReference (``image_pose = "embedded"``); with
    ``"calibration"`` a frame is placed by ProbeToReference · ``image_to_probe``."""

    probe: str = "ProbeToReference"
    image: str = "Image_Reference"
    image_pose: str = "embedded"  # "embedded" (IMAGE matrix is ImageToReference) | "calibration"
    image_to_probe: np.ndarray = field(default_factory=_default_image_to_probe)  # (4, 4), pixel → mm
    source: str = "ius"

    @property
    def named(self) -> tuple[tuple[str, str], ...]:
        return (("devices.probe", self.probe), ("devices.image", self.image))


@dataclass
class ProbeReceiver:
    probe: str  # the probe's TRANSFORM (ProbeToReference)
    image: str  # the frames' IMAGE device
    image_pose: str  # "embedded" | "calibration" (``ProbeSettings.image_pose``)
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


def default(source: str = "ius") -> ProbeSettings:
    return ProbeSettings(source=source)


def parse(source: str, data: Mapping, path=None) -> ProbeSettings:
    """Its settings from the TOML file's ``data`` (types checked by ``config``)."""
    devices, out = data.get("devices", {}), ProbeSettings(source=source)
    probe = device_name(devices.get("probe", out.probe), "devices.probe", path)
    image = device_name(devices.get("image", out.image), "devices.image", path)
    image_pose = devices.get("image_pose", out.image_pose)
    if image_pose not in IMAGE_POSES:
        raise InputError(f"devices.image_pose must be \"embedded\" or \"calibration\", got {image_pose!r}", path)
    m = out.image_to_probe
    if "image_to_probe" in data.get("calibration", {}):
        m = _calibration(data["calibration"]["image_to_probe"], path)
    return ProbeSettings(probe, image, image_pose, m, source)


def _calibration(rows, path) -> np.ndarray:
    try:
        m = np.array(rows, float)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (4, 4) or not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1]):
        raise InputError("calibration.image_to_probe must be a 4×4 matrix (rows) with last row 0 0 0 1", path)
    return m


def make(settings: ProbeSettings, shared: Shared) -> ProbeReceiver:
    return ProbeReceiver(settings.probe, settings.image, settings.image_pose, settings.image_to_probe,
                         settings.source)
