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

import numpy as np

from ..errors import InputError
from ..fitwarning import FitWarning, WarningKind, one_line
from ..mechanics.supports import RELEASES, HeldSupports, Supports
from ..registration.model import RegistrationModel
from ..registration.pipeline import Registration
from ..registration.prior import PosePrior
from ..registration.rigid import RigidResult
from .access import Role
from .contours import Contour, Origin
from .worker import cancelled

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
    ACTIONS = "actions"  # a line added to the session's action log
    POSE = "pose"  # what the surgeon states of the pose of the data


class Undone(Enum):
    DONE = "done"
    GONE = "gone"  # nothing of the action is left (removed meanwhile): undo the one before


class Action:
    """One undoable change a tab made to the shared data; each kind carries its own undo
    (``drawing``: vertices, Close, Clear; ``imaging``: planes; ``stylus``; ``live``). ``undo``
    runs under the shared lock and returns DONE, GONE, or why it cannot be undone now (the
    action is then kept)."""

    def undo(self, cs: ClientState) -> Undone | str:
        raise NotImplementedError


@dataclass
class ClientState:
    """What belongs to one browser tab."""

    client_id: int
    token: str  # identifies this tab's 2D view page
    role: Role = Role.EDITOR  # from the token of the link the tab was opened with (``access``)
    plane: int | None = None  # index of the plane shown (presets 0…, free planes from 100)
    drawing: Contour | None = None  # the contour being drawn (it is already in the session)
    # the unfinished contour on each plane this tab switched away from: clicks aimed at that plane
    # before the switch, still queued in the page, continue it there
    left: dict[int, Contour] = field(default_factory=dict)
    feature: str = "PV contour"  # a key of palette.DRAWABLE
    undo: list[Action] = field(default_factory=list)  # drawing.Action, newest last
    version: int = 0  # bumped when anything this tab shows of its own changes
    guide_step: int = 0
    error_scale_mm: float = ERROR_SCALE_MM
    error_source: str = "true"  # colour the registered surface by the "true" or the "predicted" error
    message: str = ""  # last message for the 2D view
    # device pixels per CSS pixel in this tab (its 2D view's page reports it): viser reports the 3D
    # canvas in device pixels, and the dock and the framing are laid out in CSS pixels
    pixel_ratio: float = 1.0
    successor: ClientState | None = None  # the same tab after a reload, which took over this state's work
    resume_asked: float | None = None  # when its page first asked to take a reloaded tab's work back
    parked: float | None = None  # when its connection closed (``Core.park``)
    # when its 2D view's page said it was going (a reload or a close: ``Core.going``), which a
    # loaded server hears before the closed connection, or just after it
    going: float | None = None
    # the same two moments on the browser's own clock (ms since the epoch): when this tab's 2D
    # view page began, and when it was left. A loaded server may hear the old page's beacon after
    # the new page first asked; the browser's clock still has them in the order they happened
    opened_ms: float | None = None
    going_ms: float | None = None
    address: str | None = None  # where its 2D view's requests came from (one browser's tabs share it)

    def touch(self):
        self.version += 1

    def current(self) -> ClientState:
        """This tab as it is now (itself, or what a reload made of it)."""
        cs = self
        while cs.successor is not None:
            cs = cs.successor
        return cs

    def take_over(self, old: ClientState):
        """A reloaded tab continues the work of ``old``, the same tab before the reload: its
        undo history, its contour in progress, its plane and drawing tool, its guide step."""
        self.undo[:0] = old.undo
        old.undo = []
        if self.drawing is None:
            self.drawing = old.drawing
        self.left = {**old.left, **self.left}
        if old.plane is not None:  # the plane the tab showed, not the one a panel chose as it reconnected
            self.plane = old.plane
        self.feature = old.feature
        self.guide_step = old.guide_step  # the guide goes on where the tab was, not at step 1
        old.successor = self
        self.touch()


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
    # feature → (N, 3) mm, the data the fit was made from, model frame (Registration.data_model_frame):
    # after a restart the predicted error and the next-plane suggestion need them, and the
    # session's data may have changed since (a plane added, not yet registered; a live fit's
    # frames): the LM covariance is scaled by the fit's own residuals
    data_model_frame: dict | None = field(default=None, kw_only=True)
    # why its pose is not to be believed (``Registration.pose_doubts`` in one line: undetermined,
    # too little of the liver covered), shown in red; a warm start or live re-registration never continues from it
    pose_warning: str | None = field(default=None, kw_only=True)
    # the fresh registration whose checks (the cross-validation, the predicted error over the
    # organ) this result's warnings come from: itself when fresh; for a warm start or a live
    # frame, which repeat neither check, the one it continues from. Not saved: after a
    # restart a warm start becomes a fresh fit, which checks again
    checked: Registration | None = field(default=None, kw_only=True, repr=False, compare=False)
    restored: bool = field(default=False, kw_only=True)  # read back from the session after a restart
    # the model whose basis β is in (held at the stated supports, or free-floating): its geometry
    # and errors are read off that model only. None: the free-floating model (``Core.model``)
    model: RegistrationModel | None = field(default=None, kw_only=True, repr=False, compare=False)

    def to_json(self) -> dict:
        # the prediction is kept too: it was made from the data of the fit, which for a live
        # result include frames' contours the session does not hold
        return {"run": self.run, "R": np.asarray(self.rigid.R).tolist(), "t": np.asarray(self.rigid.t).tolist(),
                "rms_mm": float(self.rigid.rms_mm), "kept": bool(self.rigid.kept),
                "beta": None if self.beta is None else np.asarray(self.beta).tolist(),
                "predicted_mm": None if self.predicted_mm is None else np.round(self.predicted_mm, 3).tolist(),
                "target_bands": [b.to_json() for b in self.target_bands], "pose_warning": self.pose_warning,
                "supports": None if self.model is None else StatedSupports(held_of(self.model)).to_json(),
                "data_model_frame": None if self.data_model_frame is None else
                {k: np.round(np.asarray(v, float), 4).tolist() for k, v in self.data_model_frame.items()}}


# the button that fits fresh is named (panels.registration.BUTTONS[RunKind.ALL]): "Re-register (warm
# start)" is itself a warm start, which does not repeat the check
CARRIED = ("at the last full registration — a warm start or a live frame does not repeat this check; "
           "\"Deformable (all data)\" does")


def checked_by(previous: RegisteredState | None, reg: Registration, warm: bool) -> Registration | None:
    """The fresh registration whose checks stand for ``reg``'s (``RegisteredState.checked``):
    ``reg`` itself when it was fitted fresh or made the checks (a live frame that started
    afresh); for a warm start or a live frame, the one the result it continued from carried."""
    if not warm or reg.support is not None or reg.organ is not None:
        return reg if reg.libr is not None else None
    return previous.checked if previous is not None else None


@dataclass(frozen=True)
class TargetBand:
    """The predicted registration error at one target's centre (mm): ê and the band that
    held the true error for 90 % of the calibration cases' points."""

    name: str
    predicted_mm: float
    lower_mm: float
    upper_mm: float
    # what the registration result warns about this target, shown after the band: the target's own
    # line (``support.TargetSupport.warning``), a pose alone's reason, or why no figure is shown
    warning: FitWarning | None = None

    def text(self, short: bool = False) -> str:
        """The band and the warning; ``short``: the warning's head only (the 2D view, whose
        frame clipped the whole line), with "(last full registration)" if it is carried."""
        warning = self.warning.text if self.warning is not None else None
        if self.warning is not None and short:
            warning = self.warning.head + (" (last full registration)" if self.warning.carried else "")
        if not np.isfinite(self.predicted_mm):  # a rigid answer: no prediction, only its warning
            return f"⚠ {warning}" if warning else ""
        band = f"predicted error {self.predicted_mm:.1f} mm ({self.lower_mm:.1f}–{self.upper_mm:.1f})"
        return band if not warning else f"{band} ⚠ {warning}"

    def to_json(self) -> list:
        """[name, ê, lower, upper] and, with a warning, its text, kind and whether it is carried
        (a session of session 39 and before kept the text alone)."""
        w = self.warning
        return [self.name, self.predicted_mm, self.lower_mm, self.upper_mm] + \
            ([w.text, w.kind.value, w.carried] if w is not None else [])

    @staticmethod
    def from_json(b: list) -> TargetBand:
        warning = None
        if len(b) > 4:  # an older session's text alone: a restored line, not carried
            kinds = {k.value: k for k in WarningKind}
            kind = kinds.get(b[5], WarningKind.SAVED) if len(b) > 5 else WarningKind.SAVED
            warning = FitWarning(kind, str(b[4]), bool(b[6]) if len(b) > 6 else False)
        return TargetBand(str(b[0]), float(b[1]), float(b[2]), float(b[3]), warning)


class PoseFrame(Enum):
    """Where the surgeon says the data's frame stands before the fit (the Registration panel's
    "Pose of the data"); the value is the session file's word."""

    UNKNOWN = "unknown"  # searched: the multi-start ICP and the pose guards
    GIVEN = "given"  # the tracker's registration puts the data in the preoperative frame
    PREVIOUS = "previous"  # the pose of the session's registration on show


STATED_SD_MM = 2.0
"""The spread offered for a pose the surgeon states without the case declaring one (mm per axis):
a landmark or fiducial registration's error (the issue's 1–2 mm, 1–2°)."""
STATED_SD_DEG = 2.0


@dataclass(frozen=True)
class StatedPose:
    """What the surgeon states of the pose: its frame and, unless unknown, its spread per axis."""

    frame: PoseFrame = PoseFrame.UNKNOWN
    sd_mm: float = STATED_SD_MM
    sd_deg: float = STATED_SD_DEG

    def __post_init__(self):
        for name in ("sd_mm", "sd_deg"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (np.isfinite(v) and v > 0):
                raise ValueError(f"pose {name}: {v!r} is not a positive number")

    @staticmethod
    def of_case(prior: PosePrior | None) -> StatedPose:
        """The case's declaration (case.toml ``[intraop.pose]``, a scene's ``[pose]``)."""
        return StatedPose() if prior is None else StatedPose(PoseFrame.GIVEN, prior.sd_mm, prior.sd_deg)

    def prior(self) -> PosePrior | None:
        return None if self.frame is PoseFrame.UNKNOWN else PosePrior(float(self.sd_mm), float(self.sd_deg))

    def words(self) -> str:
        if self.frame is PoseFrame.UNKNOWN:
            return "unknown: searched"
        whose = "as the tracker gives it" if self.frame is PoseFrame.GIVEN else "the previous registration's"
        return f"{whose}, within ±{self.sd_mm:g} mm and ±{self.sd_deg:g}°"

    def to_json(self) -> dict:
        return {"frame": self.frame.value, "sd_mm": self.sd_mm, "sd_deg": self.sd_deg}

    @staticmethod
    def from_json(d) -> StatedPose:
        """Raises ValueError (with what is wrong) for anything but a stated pose's record."""
        if not isinstance(d, dict) or set(d) != {"frame", "sd_mm", "sd_deg"}:
            raise ValueError(f"pose: {d!r} is not {{frame, sd_mm, sd_deg}}")
        return StatedPose(PoseFrame(d["frame"]), d["sd_mm"], d["sd_deg"])


@dataclass(frozen=True)
class StatedSupports:
    """What the surgeon states of where the organ is held (the Registration panel's "Organ
    held at"): the registration's basis then vanishes there in every mode; None: free-floating,
    the paper's basis."""

    held: HeldSupports | None = None

    @staticmethod
    def of_case(declared: HeldSupports | None) -> StatedSupports:
        """The case's declaration (case.toml ``[intraop.supports]``)."""
        return StatedSupports(declared)

    def words(self) -> str:
        return supports_words(self.held)

    def to_json(self) -> dict:
        h = self.held
        return {"held": None, "release": "N"} if h is None else h.as_dict()

    @staticmethod
    def from_json(d) -> StatedSupports:
        """Raises ValueError (with what is wrong) for anything but a stated supports' record:
        ``held``, ``release`` and, where given, ``stiffness_pa_per_mm`` and ``points``."""
        if not isinstance(d, dict) or not {"held", "release"} <= set(d) <= SUPPORT_KEYS:
            raise ValueError(f"supports: {d!r} is not {{held, release[, stiffness_pa_per_mm, points]}}")
        if d["held"] is None:
            return StatedSupports()
        if d["release"] not in RELEASES:
            raise ValueError(f"supports: the released side {d['release']!r} is not L, N or R")
        try:
            return StatedSupports(HeldSupports.parse(d["held"], d["release"], stiffness=d.get("stiffness_pa_per_mm"),
                                                     points=d.get("points")))
        except InputError as exc:
            raise ValueError(f"supports: {exc}") from None


SUPPORT_KEYS = {"held", "release", "stiffness_pa_per_mm", "points"}  # a stated supports' record


def supports_words(held: HeldSupports | None) -> str:
    """Where a basis holds the organ, in a surgeon's words."""
    if held is None:
        return "free-floating (no supports stated)"
    firm = "" if held.stiffness is None else f", on springs of {held.stiffness:g} Pa/mm"
    if held.held is Supports.LIGAMENTS:
        side = {"L": ", the left one released", "R": ", the right one released"}.get(held.release, "")
        return f"held at its ligaments{side}{firm}"
    if held.held is Supports.POINTS:
        return f"held at {len(held.points)} points on its surface{firm}"
    return ("held on a posterior bed" if held.held is Supports.POSTERIOR else "held at the bare area alone") + firm


def held_of(model: RegistrationModel) -> HeldSupports | None:
    """The supports ``model``'s basis is held at (None: free-floating)."""
    s = model.basis.settings
    return None if s.supports is None else HeldSupports(Supports(s.supports), s.release, s.stiffness, s.points)


class RunKind(Enum):
    """What a run fits with what; the value is the button's key, ``label`` the words shown."""

    RIGID = "rigid"
    SURFACE = "surface"
    ALL = "all"
    WARM = "warm"
    LIVE = "live"
    RESTORED = "restored"

    @property
    def label(self) -> str:
        return _LABELS[self]

    @property
    def deformable(self) -> bool:
        return self is not RunKind.RIGID

    @staticmethod
    def from_label(label: str) -> RunKind:
        """The kind a stored label names (session files store labels); unknown: RESTORED."""
        return next((k for k, v in _LABELS.items() if v == label), RunKind.RESTORED)


_LABELS = {RunKind.RIGID: "rigid", RunKind.SURFACE: "deformable, surface", RunKind.ALL: "deformable, all data",
           RunKind.WARM: "deformable, all data (warm)", RunKind.LIVE: "live (every frame)",
           RunKind.RESTORED: "restored"}


@dataclass(frozen=True, eq=False)
class WorstPoint:
    """A data point the registration left far from the model (``registration.residuals``),
    with where it came from, so that the surgeon can see it and remove it. Of a drawn
    contour only its vertices (the clicks) are listed."""

    feature: str
    residual_mm: float
    rejected: bool  # beyond the outlier cut: the fit gave it no weight
    origin: Origin
    point: tuple[float, float, float]  # tracker mm, as the session's data hold it
    where: str  # in words: the feature and its origin ("the posterior liver wall, plane 8, vertex 2 (40, 250)")
    vertex: int | None = None  # the drawn vertex it is (contours)

    def text(self) -> str:
        used = " — not used by the fit" if self.rejected else ""
        return f"{self.residual_mm:.1f} mm: {self.where}{used}"


@dataclass
class Run:
    """The registration in progress (written by the worker thread under ``Core.lock``)."""

    kind: RunKind
    points: int
    t0: float
    # the run's data (tracker mm) and each point's Origin, per feature: its worst points are
    # named from these (the session may change while it runs)
    data: dict = field(default_factory=dict)
    origins: dict = field(default_factory=dict)
    left_out: list = field(default_factory=list)  # [contours.StrayVertex] drawn vertices left out before the fit
    trace: list[tuple[float, float]] = field(default_factory=list)  # (seconds, mean true error mm) per state
    streamed: int = 0  # states received from the worker
    iteration: int = 0
    omega: float = float("nan")
    error: np.ndarray | None = None  # (M,) true error at the mesh nodes of the latest state
    state: tuple[RigidResult, np.ndarray | None] | None = None  # the latest state (rigid pose, β)
    model: RegistrationModel | None = None  # the model the run fits (its basis: the stated supports)


@dataclass
class RunEntry:
    """One row of the run table (the session's log)."""

    run: str  # RunKind.label
    points: int
    seconds: float
    iterations: int
    stop: str  # the LM stop reason, "rigid" for a rigid-only run
    updates_streamed: int = 0
    cancelled: bool = False
    trace: list[list[float]] = field(default_factory=list)  # [[seconds, mean error mm]]
    warning: str | None = None  # the fit-quality check's warning
    error_mean_mm: float | None = None  # against the truth, simulated scenes only
    error_max_mm: float | None = None
    live: str | None = None  # a live re-registration's summary
    note: str = ""
    targets_mm: dict[str, float] | None = None  # each tumour's true error at its centre, simulated scenes only
    # a deformable run whose answer is its rigid pose (the data do not support the deformation)
    pose_only: bool = False

    @property
    def kind(self) -> RunKind:
        return RunKind.from_label(self.run)

    @staticmethod
    def of(kind: RunKind, reg: Registration, points: int, seconds: float, error: np.ndarray | None = None,
           streamed: int = 0, trace=(), live: str | None = None) -> RunEntry:
        """The row of a finished (or cancelled) registration; ``error`` (M,) its true error. Its
        warning is ``reg.warnings`` in one line, with the lines a warm one carries
        (``Registration.carry``, made by the caller before)."""
        lm = reg.libr
        stopped = cancelled(reg)
        e = RunEntry(kind.label, int(points), round(float(seconds), 3), lm.iterations if lm else 0,
                     lm.stop_reason if lm else "rigid", streamed, stopped,
                     [[round(t, 3), round(v, 3)] for t, v in trace],
                     one_line(reg.warnings))
        if error is not None and not stopped:
            e.error_mean_mm, e.error_max_mm = round(float(error.mean()), 3), round(float(error.max()), 3)
        e.pose_only = kind.deformable and not stopped and lm is not None and not reg.deformed
        if live is not None:
            e.live, e.note = live, live.split(",")[0]
        return e

    def to_json(self) -> dict:
        d = {"run": self.run, "points": self.points, "seconds": self.seconds, "iterations": self.iterations,
             "stop": self.stop, "updates_streamed": self.updates_streamed, "cancelled": self.cancelled,
             "trace": self.trace}
        for k in ("warning", "error_mean_mm", "error_max_mm", "live", "targets_mm"):
            if getattr(self, k) is not None:
                d[k] = getattr(self, k)
        if self.note:
            d["note"] = self.note
        if self.pose_only:
            d["pose_only"] = True
        return d

    @staticmethod
    def from_json(d: dict) -> RunEntry:
        return RunEntry(str(d["run"]), int(d["points"]), float(d["seconds"]), int(d["iterations"]), str(d["stop"]),
                        int(d.get("updates_streamed", 0)), bool(d.get("cancelled", False)),
                        [list(map(float, x)) for x in d.get("trace", [])], d.get("warning"),
                        d.get("error_mean_mm"), d.get("error_max_mm"), d.get("live"), str(d.get("note", "")),
                        {str(k): float(v) for k, v in d["targets_mm"].items()} if d.get("targets_mm") else None,
                        bool(d.get("pose_only", False)))
