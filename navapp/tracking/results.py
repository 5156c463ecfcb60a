"""Results back to 3D Slicer over OpenIGTLink, into the scene the user already has open.

Messages (device names are at most 20 bytes in OpenIGTLink; Slicer names the nodes after
them):
- TRANSFORM ``RigidToReference``: the rigid part of the registration, navapp's model frame
  (LAS, mm) → the tracker's Reference frame;
- TRANSFORM ``PreopRASToReference``: the same for a model in 3D Slicer's RAS coordinates
  (the segmentation the case was imported from): ``RigidToReference · diag(−1, 1, 1, 1)``;
  put the preoperative segmentation under it and it lands on the tracked data;
- POINT ``NavappTargets``: registered target positions (Reference, mm), named T1, T2, …
  (Slicer shows a point list);
- POINT ``PortalCenterline``, ``HepaticCenterline``: registered vessel-centerline points;
- STRING ``NavappStatus``: one line (stage, iterations, Ω, fit quality).

Either side may listen. Slicer's OpenIGTLinkIF connector as *server* (port 18944 is taken
by PLUS, so e.g. 18945): ``ResultsSender.connect("slicer-host", 18945)``; connector as
*client*: ``ResultsSender.serve(18945)`` and point the connector at navapp. Messages queued
while nobody is connected are delivered on connection (the latest 100).
"""

from typing import Protocol

import numpy as np
import pyigtl

from ..anatomy.frames import to_case
from ..fitwarning import FitWarning, texts
from ..geometry.transforms import homogeneous

RIGID = "RigidToReference"
PREOP_RAS = "PreopRASToReference"
TARGETS = "NavappTargets"
CENTERLINES = {"portal": "PortalCenterline", "hepatic": "HepaticCenterline"}
STATUS = "NavappStatus"
COLOURS = {TARGETS: (255, 255, 0, 255), "PortalCenterline": (255, 80, 80, 255),
           "HepaticCenterline": (90, 140, 255, 255)}


class _Rigid(Protocol):
    @property
    def R(self) -> np.ndarray: ...  # (3, 3)

    @property
    def t(self) -> np.ndarray: ...  # (3,) mm

    @property
    def rms_mm(self) -> float: ...


class _Deformable(Protocol):
    @property
    def iterations(self) -> int: ...

    @property
    def stop_reason(self) -> str: ...

    @property
    def omega(self) -> float: ...


class Answer(Protocol):
    """What Slicer is told of a registration: ``registration.pipeline.Registration`` as this
    module reads it (its rigid pose, its deformable fit if any, whether that is the answer shown,
    and its warnings). Named here, not imported: tracking registers nothing, so it may not
    import the solver, not even for a type."""

    @property
    def rigid(self) -> _Rigid: ...

    @property
    def libr(self) -> _Deformable | None: ...

    @property
    def deformed(self) -> bool: ...

    @property
    def warnings(self) -> list[FitWarning]: ...

    def transform(self, points: np.ndarray) -> np.ndarray:
        """Preoperative points (P, 3) mm at their registered positions (P, 3) mm."""
        ...


def rigid_matrix(rigid: _Rigid) -> np.ndarray:
    """(4, 4) model → Reference of a ``RigidResult`` (R, t)."""
    return homogeneous(rigid.R, rigid.t)


_ASCII = str.maketrans({"≤": "<=", "≥": ">=", "Ω": "Omega", "°": " deg", "–": "-", "—": "-", "×": "x", "β": "beta",
                        "σ": "sd", "±": "+/-", "→": "->", "…": "..."})


def ascii_text(text: str) -> str:
    """``text`` in ASCII (pyigtl 0.3 encodes no other text, and its connection thread dies
    on it): the symbols navapp writes spelled out, anything else as "?"."""
    return text.translate(_ASCII).encode("ascii", "replace").decode()


def status_line(reg: Answer) -> str:
    """One line about a ``Registration``: which answer it is, and every warning it carries
    (an undetermined pose, a deformation the data do not support, a poor fit) — "fit ok"
    only when there is none, so Slicer is never told a doubtful answer is fine."""
    parts = []
    libr = reg.libr
    if libr is not None and reg.deformed:
        parts.append(f"deformable: {libr.iterations} iterations, {libr.stop_reason}, Ω {libr.omega:.3g}")
    elif libr is not None:
        parts.append(f"rigid pose shown (deformation not used): residual RMS {reg.rigid.rms_mm:.2f} mm")
    else:
        parts.append(f"rigid: residual RMS {reg.rigid.rms_mm:.2f} mm")
    warnings = texts(reg.warnings)
    parts.append("WARNING: " + " | ".join(warnings) if warnings else "fit ok")
    return ascii_text("; ".join(parts))


def registration_messages(reg: Answer, targets=None, centerlines=None, status=None) -> list:
    """pyigtl messages for a registration: ``targets`` (P, 3) and ``centerlines`` (name →
    (N, 3)) in the preoperative frame are sent at their registered positions."""
    R = rigid_matrix(reg.rigid)
    msgs = [pyigtl.TransformMessage(R, device_name=RIGID),
            pyigtl.TransformMessage(R @ to_case("RAS"), device_name=PREOP_RAS)]
    if targets is not None and len(targets):
        msgs.append(points_message(TARGETS, reg.transform(np.asarray(targets, float)),
                                   [f"T{i + 1}" for i in range(len(targets))]))
    for name, pts in (centerlines or {}).items():
        if pts is not None and len(pts):
            dev = CENTERLINES.get(name, name[:20])
            msgs.append(points_message(dev, reg.transform(np.asarray(pts, float))))
    msgs.append(pyigtl.StringMessage(ascii_text(status) if status is not None else status_line(reg),
                                     device_name=STATUS))
    return msgs


def points_message(device, points, names=None) -> pyigtl.PointMessage:
    points = np.asarray(points, float).reshape(-1, 3)
    names = names or [f"{device}-{i + 1}"[:64] for i in range(len(points))]
    rgba = COLOURS.get(device, (255, 255, 255, 255))
    return pyigtl.PointMessage(points, names=names, rgba_colors=[rgba] * len(points), device_name=device)


class ResultsSender:
    """Sends registrations to Slicer. ``link`` is a pyigtl client or server (see the
    classmethods) or anything with ``send_message(msg, wait=False)``."""

    def __init__(self, link):
        self.link = link
        self.sent = 0

    @classmethod
    def connect(cls, host: str, port: int) -> "ResultsSender":
        """navapp connects to Slicer's OpenIGTLinkIF connector in server mode (reconnects
        by itself)."""
        return cls(pyigtl.OpenIGTLinkClient(host=host, port=port, start_now=True))

    @classmethod
    def serve(cls, port: int) -> "ResultsSender":
        """navapp listens on 127.0.0.1:``port`` for Slicer's connector in client mode
        (0: a free port, ``.port``)."""
        from .replay import quiet_server

        server = quiet_server(port)
        server.start()
        return cls(server)

    @property
    def port(self) -> int:
        addr = getattr(self.link, "server_address", None)
        return addr[1] if addr else self.link.port

    @property
    def connected(self) -> bool:
        return bool(getattr(self.link, "is_connected", lambda: True)())

    def send(self, messages) -> int:
        for m in messages:
            # packed here first: a message pyigtl cannot encode (e.g. non-ASCII text) raises
            # in the caller instead of killing the connection thread, which packs it again
            m.pack()
        for m in messages:
            self.link.send_message(m, wait=False)
        self.sent += len(messages)
        return len(messages)

    def send_registration(self, reg: Answer, targets=None, centerlines=None, status=None) -> int:
        return self.send(registration_messages(reg, targets, centerlines, status))

    def send_status(self, text: str) -> int:
        text = ascii_text(text)
        return self.send([pyigtl.StringMessage(text, device_name=STATUS)])

    def close(self):
        self.link.stop()
