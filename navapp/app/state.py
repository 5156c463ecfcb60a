"""The viewer's state, split by who owns it. No viser here.

*Shared* (one per server, in ``core.Core``, guarded by ``Core.lock``): the scene data, the session (what the
users entered), the registration model and the current registered result. It changes only
through the rooms' actions, which every browser then sees.

*Per browser* (``ClientState``): the plane this browser looks at, the contour it is
drawing, its own undo history, its guide step and its colour scale. Two tabs therefore
never move each other's clicks or undo each other's work.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

from ..registration.rigid import RigidResult
from .contours import Contour

if TYPE_CHECKING:
    from .drawing import Action

ERROR_SCALE_MM = 15.0  # default top of the error colour scale: the same colour means the same error in every run


class Change(Enum):
    """What changed, so each view redraws only what shows it."""

    STATUS = "status"  # the start-up stage
    SCENE = "scene"  # the scene data and session are loaded
    MODEL = "model"  # the registration model is ready
    DATA = "data"  # collected data, planes added, contours
    PLANE = "plane"  # the plane one tab shows
    RUN = "run"  # a registration started or failed
    RESULT = "result"  # a registration finished: the result on show, the log
    LOG = "log"
    LIVE = "live"  # tracker status, recording, live re-registration


@dataclass
class ClientState:
    """What belongs to one browser tab."""

    client_id: int
    token: str  # identifies this tab's 2D view page
    plane: int | None = None  # index of the plane shown (presets 0…, free planes from 100)
    drawing: Contour | None = None  # the contour being drawn (it is already in the session)
    feature: str = "PV contour"  # a key of palette.DRAWABLE
    undo: list[Action] = field(default_factory=list)  # drawing.Action, newest last
    version: int = 0  # bumped when anything this tab shows of its own changes
    guide_step: int = 0
    error_scale_mm: float = ERROR_SCALE_MM
    error_source: str = "true"  # colour the registered surface by the "true" or the "predicted" error
    message: str = ""  # last message for the 2D view

    def touch(self):
        self.version += 1


@dataclass
class StateGeometry:
    """Where one registered state (rigid pose, β) puts the model, computed once per state
    for every browser, the 2D overlays and the distance readouts."""

    rigid: RigidResult | None  # None: nothing registered (preoperative, as-is)
    beta: np.ndarray | None
    surfaces: dict  # "liver" / "portal" / "hepatic" → ((V, 3) tracker mm, (F, 3) faces); {} unregistered
    targets: list  # [anatomy.targets.Target], carried by the state


@dataclass
class RegisteredState:
    """The registered model on show: rigid pose, β (None for a rigid-only result) and,
    for simulated scenes, the per-node error against the truth."""

    run: str  # the run's label (runs.RunKind.label), e.g. "deformable, all data"
    rigid: RigidResult
    beta: np.ndarray | None
    node_error_mm: np.ndarray | None = None  # (M,) over the mesh nodes, when the truth is known
    predicted_mm: np.ndarray | None = None  # (S,) predicted error at the surface nodes (no truth needed)
    target_bands: list[TargetBand] = field(default_factory=list)  # predicted error at each target

    def to_json(self) -> dict:
        # the prediction is kept too: it was made from the data of the fit, which for a live
        # result include frames' contours the session does not hold
        return {"run": self.run, "R": np.asarray(self.rigid.R).tolist(), "t": np.asarray(self.rigid.t).tolist(),
                "rms_mm": float(self.rigid.rms_mm),
                "beta": None if self.beta is None else np.asarray(self.beta).tolist(),
                "predicted_mm": None if self.predicted_mm is None else np.round(self.predicted_mm, 3).tolist(),
                "target_bands": [b.to_json() for b in self.target_bands]}


@dataclass(frozen=True)
class TargetBand:
    """The predicted registration error at one target's centre (mm): ê and the band that
    held the true error for 90 % of the calibration cases' points."""

    name: str
    predicted_mm: float
    lower_mm: float
    upper_mm: float
    warning: str | None = None  # what the registration result warns about this target, shown after the band

    def text(self) -> str:
        band = f"predicted error {self.predicted_mm:.1f} mm ({self.lower_mm:.1f}–{self.upper_mm:.1f})"
        return band if not self.warning else f"{band} ⚠ {self.warning}"

    def to_json(self) -> list:
        return [self.name, self.predicted_mm, self.lower_mm, self.upper_mm] + ([self.warning] if self.warning else [])

    @staticmethod
    def from_json(b: list) -> TargetBand:
        return TargetBand(str(b[0]), float(b[1]), float(b[2]), float(b[3]), str(b[4]) if len(b) > 4 else None)
