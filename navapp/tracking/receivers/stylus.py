"""The tracked stylus, received: its tip's pose stream (TRANSFORM ``StylusTipToReference``
by default), each sample offered to the digitiser, which records tip points at its rate
while digitising is on. Its settings: ``[devices] stylus`` in the tracking TOML file."""

from collections.abc import Mapping
from dataclasses import dataclass

from ..digitiser import Digitiser
from ..events import StylusSample, ToolStatus
from .base import Event, Message, Shared, device_name, pose_matrix, seen

KEYS: dict[str, dict[str, type]] = {"devices": {"stylus": str}}  # its keys in the tracking TOML file
TABLES: tuple[str, ...] = ()


@dataclass(frozen=True)
class StylusSettings:
    device: str = "StylusTipToReference"  # the tip's TRANSFORM, PLUS's name for a pivot-calibrated stylus
    source: str = "stylus"

    @property
    def named(self) -> tuple[tuple[str, str], ...]:
        return (("devices.stylus", self.device),)


@dataclass
class StylusReceiver:
    device: str  # the tip's TRANSFORM (StylusTipToReference)
    digitiser: Digitiser
    source: str = "stylus"
    latest: StylusSample | None = None

    @property
    def devices(self) -> tuple[str, ...]:
        return (self.device,)

    def takes(self, mtype: str, device: str) -> bool:
        return mtype == "TRANSFORM" and device == self.device

    def receive(self, message: Message) -> Event | None:
        m = pose_matrix(message)
        return StylusSample(message.t, message.t_sent, m[:3, 3].copy(), m)

    def keep(self, event: Event) -> None:
        if isinstance(event, StylusSample):
            self.latest = event
            self.digitiser.feed(event)  # in the client thread: recording waits for nobody

    def fresh(self, status: Mapping[str, ToolStatus]) -> bool:
        return seen(status, self.device)


def default(source: str = "stylus") -> StylusSettings:
    return StylusSettings(source=source)


def parse(source: str, data: Mapping, path=None) -> StylusSettings:
    """Its settings from the TOML file's ``data`` (types checked by ``config``)."""
    device = data.get("devices", {}).get("stylus", StylusSettings.device)
    return StylusSettings(device_name(device, "devices.stylus", path), source)


def make(settings: StylusSettings, shared: Shared) -> StylusReceiver:
    return StylusReceiver(settings.device, shared.digitiser, settings.source)
