"""Registrations to 3D Slicer over OpenIGTLink (``navapp serve --slicer``): the rigid pose,
the registered targets and centerlines, and a status line, at most ``MAX_HZ`` a second
while live. No viser here.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from ..anatomy.model import VESSELS

if TYPE_CHECKING:
    from ..anatomy.model import PreopModel
    from ..registration.pipeline import Registration
    from ..tracking.results import ResultsSender

MAX_HZ = 10.0


class Slicer:
    def __init__(self, preop: PreopModel, sender: ResultsSender | None):
        self.preop = preop
        self.sender = sender  # None: not sending
        self.error: str | None = None  # the last send's failure
        self._sent = 0.0

    def send(self, reg: Registration, throttle: bool = False):
        sender = self.sender
        if sender is None:
            return
        now = time.monotonic()
        if throttle and now - self._sent < 1.0 / MAX_HZ:
            return
        self._sent = now
        from ..tracking.results import status_line

        pre = self.preop
        centres = np.array([t.centre for t in pre.targets]) if pre.targets else None
        lines = {}
        for n in VESSELS:
            cl = pre.centerline(n)
            if cl is not None:
                lines[n] = cl.points
        try:
            sender.send_registration(reg, centres, lines, status=status_line(reg))
        except Exception as exc:  # Slicer gone: the viewer carries on
            self.error = f"{exc.__class__.__name__}: {exc}"
