"""What every receiver shares: the message it is handed, the protocols it and its settings
implement, what the client gives every receiver, the checks of a TRANSFORM's matrix and of
a settings value read from the tracking TOML file."""

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from pyigtl.messages import MessageBase

from ...errors import InputError
from ..digitiser import Digitiser
from ..events import ProbePose, ProbeSample, SourcePoints, StylusSample, ToolStatus, TransformSample, as_matrix

Event = StylusSample | ProbePose | ProbeSample | SourcePoints | TransformSample
"""What a receiver makes of a message (``events.py``)."""


@dataclass(frozen=True)
class Message:
    """One OpenIGTLink message, its CRC checked and its body decoded by pyigtl, in order
    (not older than its device's last): what the client hands a receiver."""

    mtype: str  # "TRANSFORM", "IMAGE", "POINT", …
    device: str
    t: float  # the receiving machine's time.monotonic() when it was parsed
    t_sent: float  # its own OpenIGTLink timestamp (s since 1970, the sender's clock)
    body: MessageBase


class ToolSettings(Protocol):
    """One tracked data source's own settings, read from the tracking TOML file by its
    receiver module's ``parse`` (the module's ``KEYS`` and ``TABLES`` say which part of the
    file is its own). ``source``: its ``features.TABLE`` source. ``named``: each OpenIGTLink
    device it listens to, as (its key in the file, its name): no two tools may share a name.
    """

    @property
    def source(self) -> str: ...

    @property
    def named(self) -> tuple[tuple[str, str], ...]: ...


@dataclass(frozen=True)
class Shared:
    """What the client gives every receiver beside its own settings: the stylus's digitiser
    and the watchdog's ``stale_s`` (s; a pose older than this places nothing)."""

    digitiser: Digitiser
    stale_s: float = 0.2


class Receiver(Protocol):
    """The receiving side of one tracked data source (a ``features.TABLE`` ``source``).

    ``devices``: the OpenIGTLink devices the watchdog watches for it, in the order the
    viewer lists them. ``takes(mtype, device)``: the messages that are its own.
    ``receive(message)``: the event it makes of one (None: nothing); a message it cannot
    use raises ``ValueError`` with the reason (the client skips it as malformed and keeps
    the connection). ``keep(event)``: the client accepted the event (counted, watched):
    the receiver keeps it as its latest (and the stylus's digitiser records it).
    ``fresh(status)``: what it keeps may be shown and used now (``status``: the watchdog's
    ``ToolStatus`` per device): a lost tool is not drawn where it was last seen.
    """

    source: str

    @property
    def devices(self) -> tuple[str, ...]: ...

    def takes(self, mtype: str, device: str) -> bool: ...

    def receive(self, message: Message) -> Event | None: ...

    def keep(self, event: Event) -> None: ...

    def fresh(self, status: Mapping[str, ToolStatus]) -> bool: ...


def seen(status: Mapping[str, ToolStatus], device: str) -> bool:
    """The watchdog calls ``device`` seen now."""
    st = status.get(device)
    return st is not None and st.state == "seen"


def pose_matrix(message: Message) -> np.ndarray:
    """A TRANSFORM's 4×4 (mm), or ``ValueError`` when it is not a finite homogeneous matrix."""
    m = as_matrix(message.body.matrix)  # a TransformMessage
    if not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1]):
        raise ValueError("not a finite homogeneous 4×4 matrix")
    return m


def typed(value, kind: type, key: str, path) -> object:
    """``value`` as a ``kind`` (an int is a float), or ``InputError`` naming ``key``."""
    if kind is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, kind) and not isinstance(value, bool):
        return value
    raise InputError(f"{key} must be a {kind.__name__}, got {value!r}", path)


def device_name(value: str, key: str, path) -> str:
    """``value`` when it can be an OpenIGTLink device name (1–20 bytes), else ``InputError``."""
    if not value or len(value.encode()) > 20:
        raise InputError(f"{key} must be 1–20 bytes (an OpenIGTLink device name), got {value!r}", path)
    return value
