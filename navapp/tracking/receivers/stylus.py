"""The tracked stylus, received: its tip's pose stream (TRANSFORM ``StylusTipToReference``
by default), each sample offered to the digitiser, which records tip points at its rate
while digitising is on."""

from collections.abc import Mapping
from dataclasses import dataclass

from ..config import TrackingConfig
from ..digitiser import Digitiser
from ..events import StylusSample, ToolStatus
from .base import Event, Message, pose_matrix, seen


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


def make(config: TrackingConfig, digitiser: Digitiser) -> StylusReceiver:
    return StylusReceiver(config.stylus, digitiser)
