"""What the tracking client hands to the app: typed, immutable events.

Units: mm, seconds. ``t`` is the receiving machine's ``time.monotonic()`` when the message
was parsed; ``t_sent`` is the message's own OpenIGTLink timestamp (seconds since 1970, set
by the sender at acquisition). Coordinates are in the tracker's Reference frame, passed
through unchanged (see ``navapp.tracking`` for why that is right for registration).
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StylusSample:
    t: float
    t_sent: float
    tip: np.ndarray  # (3,) mm, Reference: the translation of StylusTipToReference
    matrix: np.ndarray  # (4, 4) StylusTipToReference as received


@dataclass(frozen=True)
class ProbePose:
    t: float
    t_sent: float
    probe_to_reference: np.ndarray  # (4, 4) mm


@dataclass(frozen=True)
class ProbeSample:
    """One ultrasound frame with its pose. ``image_to_reference`` maps homogeneous pixel
    coordinates (col, row, 0, 1) to mm in Reference (the spacing is in its columns), as
    navapp's ``Probe.image_to_probe`` does for the probe frame."""
    t: float
    t_sent: float
    image_to_reference: np.ndarray  # (4, 4)
    image: np.ndarray  # (H, W) uint8 (other scalar types are passed as received)
    spacing_mm: tuple  # (column spacing, row spacing) mm/pixel
    pose_source: str  # "embedded" (IMAGE matrix) or "calibration" (ProbeToReference · ImageToProbe)
    pose_age_s: float = 0.0  # calibration mode: how much older the probe pose is than the image


@dataclass(frozen=True)
class SourcePoints:
    """Points of a data source (``features.SOURCED``: a laparoscope's depth points), from an
    OpenIGTLink POINT message whose device name is the feature's."""
    t: float
    t_sent: float
    feature: str
    points: np.ndarray  # (N, 3) mm, Reference


@dataclass(frozen=True)
class TransformSample:
    """Any other TRANSFORM the server sends (the app may show it; nothing uses it)."""
    t: float
    t_sent: float
    name: str
    matrix: np.ndarray


@dataclass(frozen=True)
class ToolStatus:
    """Watchdog state of one device: "seen" (fresh), "stale" (older than stale_s) or
    "missing" (never seen, or older than missing_s). ``age_s`` is None when never seen."""
    tool: str
    state: str
    age_s: float | None


@dataclass(frozen=True)
class ConnectionStatus:
    connected: bool
    address: str  # "host:port"
    connects: int  # successful connections so far (2 and more: reconnected)
    reason: str = ""  # why the last connection ended, or ""


@dataclass(frozen=True)
class Skipped:
    """A message that was logged and dropped: malformed (bad CRC, undecodable body),
    unknown type, out of order (older than the last one of its device), or garbage (not
    OpenIGTLink at all: the connection is dropped and reopened, the stream cannot be
    resynchronised)."""
    t: float
    kind: str  # "malformed" | "unknown" | "out_of_order" | "garbage"
    device: str
    detail: str


def as_matrix(m) -> np.ndarray:
    return np.array(m, dtype=float).reshape(4, 4)
