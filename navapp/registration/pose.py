"""Is the rigid pose right, and is it determined? Two checks on the rigid stage.

**Keep a good given pose.** Data that arrive already aligned (the tracker frame is the
preoperative one, or a previous registration put them there) lie on the undeformed model
except where the organ moved. ICP then slides the model to share out the local misfit —
on a partial, smooth surface it can do so almost for free — and the deformable fit
starts from a pose that is wrong everywhere. ``choose_pose`` runs a *trimmed* ICP from the
given pose (each step fits only the half of the surface points nearest the model: a local
deformation of fewer than half of them does not pull it) and keeps the given pose when
that fit moves the data less than ``POSE_RULE.moved_mm`` and leaves a part of them on the
model (``POSE_RULE.aligned``: a global sag leaves only the points where the surfaces cross).

**Or the pose most of the data agree on, near the given one.** A large dent moves most of a
partial scan by millimetres, so the trimmed fit moves more than the margin; the multi-start
ICP then fits the whole scan, dent included, and on a partial patch it can find a pose tens
of millimetres away that fits every point a little. The trimmed fit's pose (``LOCAL``) is
taken instead when most surface points lie on the model there (a fraction
``POSE_RULE.consensus`` within ``POSE_RULE.on_mm``) and clearly more than at ICP's pose
(``POSE_RULE.consensus_margin``), and the fit stayed within ``POSE_RULE.local_mm`` of the
given pose: a consensus of data on the model, as in RANSAC, that a pose sharing out a local
misfit does not reach. A global sag or a tracker offset puts no
pose's consensus that high, and ICP's pose is taken as before.

**Not a turn no tracker makes.** A partial scan of a lobe that swung away fits the undeformed
organ best turned as far as the lobe (82° and 125° on the neo-Hookean tool cases). A turn
beyond ``POSE_RULE.tracker_turn_deg`` that the pose alone does not confirm (it leaves most data
off the model) puts the answer in doubt, and the given pose is held (``prefer_given``); where
such a turn is taken, one line says the turn and that the tracker or the scanned part is that
far off.

**Sliding directions.** The point-to-plane normal matrix A = Σ w aᵢaᵢᵀ, aᵢ = ((xᵢ − c) × nᵢ / L,
nᵢ) (rotation scaled by the data radius L, so both halves are mm), is the inverse of the
pose's ICP covariance up to the noise. An eigenvector with a small eigenvalue is a motion
that changes no distance to first order: a partial sphere turns about its centre, a
cylinder slides along its axis, a plane slides in itself. ``pose_determinacy`` reports
those motions and one line when there are any.
"""

import math
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from ..features import RIGID
from .model import RegistrationModel
from .objective import correspond
from .rigid import RigidResult, _screen_geometry
from .rotation import rotation_angle


@dataclass(frozen=True)
class PoseRule:
    """Which pose the rigid stage answers with (``choose_pose``)."""
    keep: float = 0.5  # the trimmed fit uses this best-fitting fraction of the surface data
    # the given pose is kept when the trimmed fit moves the data less (RMS, mm); measured: 8.2–12.9 mm
    # on the nine direct study cases (a global sag), 1.1–3.1 mm on the tool cases with a dent under
    # the data (docs/decisions/local-loads.md, "Local loads")
    moved_mm: float = 4.0
    # ... and part of the data lie on the model there: a global sag leaves the trimmed fit stuck
    # on the points where the two surfaces cross (phantom2-N: 3.3 mm moved, 12 % on the model; from
    # a 5° / 10 mm offset with shifted labels 3.0 mm and 31 %; the tool cases whose pose is kept
    # 47–93 %)
    aligned: float = 0.4
    # a surface point is on the model within this distance (mm): about 3 × the tracker noise
    # the scenes simulate (0.3 mm sd)
    on_mm: float = 1.0
    # the trimmed fit's pose is taken when at least this fraction of the points is on the model
    # there, and this much more than at ICP's pose (docs/decisions/local-loads.md, "Local loads")
    consensus: float = 0.65
    consensus_margin: float = 0.15
    # ... and only when the trimmed fit moved the data less than this (RMS, mm): a correction
    # of the given pose, not a new pose. From a 5° / 10 mm offset on phantom1-L (a global sag)
    # the trimmed fit ended 11.7 mm away with 68 % of the points on the model, at a worse pose
    # than ICP's; on the deep-dent tool cases it moved 4.2–7.0 mm
    local_mm: float = 8.0
    # when the answer from ICP's pose is in doubt (a poor fit, or a deformation the data do not
    # support), the given pose (held, with LIBR) is the answer if its data residual is within this
    # factor of ICP's: the move was not earned by a better fit (``prefer_given``). Measured (pooled
    # RMS, given ÷ ICP, docs/decisions/local-loads.md "Local loads"): at most 1.09 where the given pose was right,
    # at least 1.23 where ICP's was
    given_ratio: float = 1.15
    # ... and the given pose is held when ICP's pose turns the organ by more than this from it
    # (degrees) and the pose alone leaves most data off the model (under ``consensus`` within
    # ``on_mm``), whatever the residuals: a tracker's registration is not that far off, so such a
    # turn is the multi-start search's guess at a lobe that moved, not a correction of the
    # tracker (docs/decisions/registration.md, "A turn no tracker makes"). The robustness study's largest
    # offset is 20°; its starts turn by 15° and by the principal axes' flips (90°, 180°)
    tracker_turn_deg: float = 45.0


POSE_RULE = PoseRule()
WEAK_RATIO = 1e-2  # an eigenvalue below this × the largest: a sliding direction (a 10 mm-faceted ball: 5e-3)
MAX_POINTS = 2000  # per feature: the trimmed fit and the normal matrix need no more


def _surface_points(model: RegistrationModel, data: dict, pose: RigidResult, features=RIGID):
    """(points in the model frame, their closest points, unit normals) of the surface data."""
    Ps, Qs, Ns = [], [], []
    for name, Y in data.items():
        if name not in features or name == "fiducials" or not len(Y):
            continue
        feat = model.feature_for(name)
        if feat.kind != "surface":
            continue
        Y = np.asarray(Y)[:: -(-len(Y) // MAX_POINTS)]
        Ym = pose.inverse(Y)
        # the rest geometry never changes: its k-d tree is built once per model (the trimmed
        # fit calls this up to 30 times; a warm re-registration once per frame)
        c = correspond(feat, feat.rest, Ym, tree=_screen_geometry(model, name)[0])
        Ps.append(Ym)
        Qs.append(c.S @ feat.rest)
        Ns.append(np.asarray(c.direction))
    if not Ps:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    return np.vstack(Ps), np.vstack(Qs), np.vstack(Ns)


def trimmed_pose(model: RegistrationModel, data: dict, start: RigidResult, keep: float = POSE_RULE.keep,
                 iterations: int = 30, tol_mm: float = 1e-3,
                 at_start: tuple | None = None) -> tuple[RigidResult, float]:
    """Trimmed point-to-plane ICP from ``start``: each step fits only the ``keep`` fraction
    of surface points nearest the model (least trimmed squares), so a deformation that
    moves fewer than that fraction of the data does not move the pose. Returns the pose and
    how far it moved the data from ``start`` (RMS, mm). ``at_start``: ``_surface_points`` at
    ``start``, when the caller has it (``choose_pose``), not searched again."""
    from ..geometry.transforms import rotvec_matrix

    R, t = start.R.copy(), start.t.copy()
    Y0 = None
    kept, last = np.inf, (R, t)  # the trimmed objective at the pose the last step left, and that pose
    for i in range(iterations):
        pose = RigidResult(R, t, 0, 0.0)
        P, Q, N = at_start if i == 0 and at_start is not None else _surface_points(model, data, pose)
        if len(P) < 6:
            return start, 0.0
        if Y0 is None:
            Y0 = P.copy()
        r = np.einsum("ij,ij->i", N, P - Q)
        best = np.argsort(np.abs(r))[: max(6, int(keep * len(r)))]
        # a descent method: a step that raised the trimmed objective (the kept points' squared
        # distances, searched afresh) is the linearisation failing, not a better pose, and is
        # undone. A line of stylus points leaves a rotation about it and a slide along it
        # nearly free; solved whole, the steps along them grew until the pose stood 1e221 mm
        # off and the closest-point search read past its arrays (docs/decisions/live.md)
        objective = float(np.sum(r[best] ** 2))
        if not objective <= kept:
            R, t = last
            break
        kept, last = objective, (R, t)
        c = P[best].mean(0)
        a = np.hstack([np.cross(P[best] - c, N[best]), N[best]])
        x = np.linalg.lstsq(a, -r[best], rcond=None)[0]
        if not np.isfinite(x).all():
            return start, float("inf")
        w, v = x[:3], x[3:] - np.cross(x[:3], c)  # rotation about c → about the origin
        Rd = rotvec_matrix(w)
        R = R @ Rd.T
        t = t - R @ v
        if np.linalg.norm(w) * np.linalg.norm(P - c, axis=1).max() + np.linalg.norm(x[3:]) < tol_mm:
            break
    if Y0 is None:
        return start, 0.0
    moved = RigidResult(R, t, 0, 0.0).inverse(start.apply(Y0))
    shift = float(np.sqrt(np.mean(np.sum((moved - Y0) ** 2, axis=1))))
    return RigidResult(R, t, 0, 0.0), shift if np.isfinite(shift) else float("inf")


class PoseSource(Enum):
    """Where the rigid stage's pose came from."""
    GIVEN = "given"  # the tracker's pose: the data lie on the undeformed model
    LOCAL = "local"  # the trimmed fit from the given pose: most data lie on the model there
    FITTED = "fitted"  # the multi-start ICP's pose
    # the tracker's pose, held: ICP's pose, with deformation, fitted the data no better (``prefer_given``)
    GIVEN_FITS = "given-fits"
    # the tracker's pose, held: ICP's pose turned the organ further than a tracker errs, and the
    # pose alone left most data off the model (``prefer_given``)
    GIVEN_TURN = "given-turn"


@dataclass(frozen=True)
class PoseFits:
    """The deformable fit from ICP's pose beside the same fit with the given pose held
    (``prefer_given``), made where the answer from ICP's pose is in doubt."""
    fitted_rms_mm: float  # the data residual of the fit from ICP's pose (pooled RMS, mm)
    given_rms_mm: float  # ... and of the fit with the given pose held
    shift_mm: float  # how far ICP's pose moves the data from where they are given (RMS, mm)

    def as_dict(self) -> dict:
        return {"fitted_rms_mm": round(self.fitted_rms_mm, 3), "given_rms_mm": round(self.given_rms_mm, 3),
                "fitted_shift_mm": round(self.shift_mm, 3)}


def turn_deg(pose: RigidResult) -> float:
    """How far ``pose`` turns the organ from the given (identity) pose (degrees, 0–180)."""
    return float(np.degrees(rotation_angle(pose.R)))


def shift_mm(pose: RigidResult, data: dict) -> float:
    """How far ``pose`` moves the data from where they are given (RMS, mm)."""
    pts = np.vstack([p for p in data.values() if len(p)]) if data else np.zeros((0, 3))
    return float(np.sqrt(np.mean(np.sum((pose.inverse(pts) - pts) ** 2, axis=1)))) if len(pts) else 0.0


@dataclass
class PoseChoice:
    """The rigid stage's decision between the given pose, the trimmed fit from it and ICP's."""
    source: PoseSource
    moved_mm: float | None  # how far the trimmed fit from the given pose moved the data (RMS)
    # fraction of the surface points on the model (within ``PoseRule.on_mm``) at each pose looked at
    on_model: dict = field(default_factory=dict)
    local: RigidResult | None = None  # the trimmed fit's pose (model → data)
    # how far ICP's pose turns the organ from the given one (degrees; ``turn_deg``), once ICP's
    # pose is final (the caller's ``with_turn``)
    turn_deg: float | None = None
    # the two deformable fits, where the answer from ICP's pose was in doubt (``prefer_given``)
    fits: PoseFits | None = None

    @property
    def kept(self) -> bool:
        """The pose is one the data fix without ICP (given or local): LIBR keeps it (τ, θ fixed)."""
        return self.source is not PoseSource.FITTED

    @property
    def given(self) -> bool:
        """The answer's pose is the tracker's own (kept as aligned, or as fitting no worse)."""
        return self.source in (PoseSource.GIVEN, PoseSource.GIVEN_FITS, PoseSource.GIVEN_TURN)

    def unconfirmed_turn(self, rule: PoseRule = POSE_RULE) -> bool:
        """ICP's pose turns the organ further than a tracker's registration errs
        (``rule.tracker_turn_deg``) and the pose alone leaves most surface data off the model
        (under ``rule.consensus`` within ``rule.on_mm``): the answer from it is in doubt."""
        return self.source is PoseSource.FITTED and (self.turn_deg or 0.0) > rule.tracker_turn_deg and \
            self.on_model.get(PoseSource.FITTED, 0.0) < rule.consensus

    @property
    def warning(self) -> str | None:
        f, turn = self.fits, self.turn_deg or 0.0
        if f is None or self.source is PoseSource.FITTED:
            # ICP's pose after the comparison is one the fit earned (``prefer_given``): no line says
            # its pose is in doubt
            if self.source is PoseSource.FITTED and turn > POSE_RULE.tracker_turn_deg:
                # the answer is not in doubt, yet a turn no tracker's registration needs: either
                # the tracker was that far off, or the scanned part of the organ turned as a whole
                # (a lobe lifted) and the rest follows it wrongly; the data cannot tell which
                return (f"ICP's pose turns the organ {turn:.0f}° from the given pose, further than a tracker's "
                        f"registration errs ({POSE_RULE.tracker_turn_deg:.0f}°): either the tracker's registration "
                        "is that far off or the scanned part of the organ moved as a whole — check the tracker's "
                        "registration and add data over the rest of the organ")
            return None
        moved = f"{f.shift_mm:.0f} mm" + (f" and turned it {turn:.0f}°" if turn >= 5.0 else "")
        if self.source is PoseSource.GIVEN_TURN:
            on = self.on_model.get(PoseSource.FITTED, 0.0)
            return (f"ICP's pose is not taken: it moved the organ {moved} from the given pose, further than a "
                    f"tracker's registration errs ({POSE_RULE.tracker_turn_deg:.0f}°), and the pose alone leaves "
                    f"most of the data off the model there ({on:.0%} within {POSE_RULE.on_mm:g} mm) — the given pose "
                    f"is kept (the deformable fit leaves the data {f.fitted_rms_mm:.2f} mm RMS off at ICP's pose, "
                    f"{f.given_rms_mm:.2f} mm at the given one); neither pose is determined by these data: check the "
                    "tracker's registration and add data away from where the organ moved")
        if self.source is not PoseSource.GIVEN_FITS:
            return None
        return (f"ICP's pose is not earned by the fit: it moved the organ {moved} from the given pose, but the "
                f"deformable fit there leaves the data {f.fitted_rms_mm:.2f} mm RMS off against "
                f"{f.given_rms_mm:.2f} mm at the given pose — the given pose is kept; add data away from where "
                "the organ moved")

    def as_dict(self) -> dict:
        out = {"source": self.source.value,
               "trimmed_fit_moved_mm": None if self.moved_mm is None else round(self.moved_mm, 3),
               "kept_given": self.given,
               "on_model_fraction": {k.value: round(v, 3) for k, v in self.on_model.items()}}
        if self.turn_deg is not None:
            out["fitted_turn_deg"] = round(self.turn_deg, 2)
        if self.fits is not None:
            out.update(self.fits.as_dict())
        if self.warning:
            out["warning"] = self.warning
        return out


def _distances(model: RegistrationModel, data: dict, pose: RigidResult) -> np.ndarray:
    P, Q, _ = _surface_points(model, data, pose)
    return np.linalg.norm(P - Q, axis=1)


def on_model_fraction(model: RegistrationModel, data: dict, pose: RigidResult, on_mm: float) -> float:
    """Fraction of the surface data within ``on_mm`` of the model at ``pose``."""
    d = _distances(model, data, pose)
    return float(np.mean(d < on_mm)) if len(d) else 0.0


def rms_on_model(model: RegistrationModel, data: dict, pose: RigidResult) -> float:
    """RMS distance (mm) of the surface data to the model at ``pose``: a kept pose's
    ``rms_mm`` (what the viewer and Slicer report as the rigid fit's residual)."""
    d = _distances(model, data, pose)
    return float(np.sqrt(np.mean(d ** 2))) if len(d) else 0.0


Trimmed = tuple[RigidResult, float, np.ndarray]  # ``trimmed_from_given``: pose, RMS moved (mm), distances (mm)
_NOT_MADE: "Trimmed | None" = (RigidResult(np.eye(3), np.zeros(3), 0, 0.0), math.nan, np.zeros(0))


def trimmed_from_given(model: RegistrationModel, data: dict, given: RigidResult,
                       rule: PoseRule = POSE_RULE) -> Trimmed | None:
    """``choose_pose``'s part that reads only the data and the given pose: the trimmed fit from
    ``given`` (``trimmed_pose``), how far it moved the data (RMS, mm) and the surface data's
    distances (N,) mm to the model at its pose; None with fewer than six surface points. It does
    not depend on the multi-start search, so ``register`` makes it beside that search on the
    second core (docs/decisions/speed.md, "The fresh registration's independent parts side by side")."""
    at_given = _surface_points(model, data, given)
    if len(at_given[0]) < 6:
        return None
    # a rigid offset smaller than the margin is kept too (and LIBR cannot take it out): a
    # clause that also refused poses whose trimmed fit halved the median distance caught a
    # 2 mm shift but kept no tool case's pose either (docs/decisions/local-loads.md, "Local loads")
    local, moved = trimmed_pose(model, data, given, rule.keep, at_start=at_given)
    return local, moved, _distances(model, data, local)


def choose_pose(model: RegistrationModel, data: dict, given: RigidResult, fitted: RigidResult | None = None,
                rule: PoseRule = POSE_RULE, trimmed: Trimmed | None = _NOT_MADE) -> PoseChoice:
    """The given pose when the best-fitting part of the surface data already lies on the
    undeformed model there (the trimmed fit, ``trimmed_pose``, moves them less than
    ``rule.moved_mm`` and leaves a fraction ``rule.aligned`` on the model); else the
    trimmed fit's own pose when it stayed near (``rule.local_mm``) and most data are on the
    model there, clearly more than at ``fitted`` (ICP's); else ``fitted`` (module doc).
    The pose returned as ``local`` is marked ``kept``. ``trimmed``: ``trimmed_from_given``'s
    answer for these data and ``given``, when the caller made it ahead (beside the multi-start
    search, which it does not depend on)."""
    made = trimmed_from_given(model, data, given, rule) if trimmed is _NOT_MADE else trimmed
    if made is None:
        return PoseChoice(PoseSource.FITTED, None)
    local, moved, d = made
    on = {PoseSource.LOCAL: float(np.mean(d < rule.on_mm))}
    if moved < rule.moved_mm and on[PoseSource.LOCAL] >= rule.aligned:
        return PoseChoice(PoseSource.GIVEN, moved, on)
    if fitted is not None:
        on[PoseSource.FITTED] = on_model_fraction(model, data, fitted, rule.on_mm)
    local = replace(local, rms_mm=float(np.sqrt(np.mean(d ** 2))), kept=True)
    if moved < rule.local_mm and on[PoseSource.LOCAL] >= rule.consensus and \
            on[PoseSource.LOCAL] >= on.get(PoseSource.FITTED, 0.0) + rule.consensus_margin:
        return PoseChoice(PoseSource.LOCAL, moved, on, local)
    return PoseChoice(PoseSource.FITTED, moved, on, local)


def prefer_given(choice: PoseChoice, fits: PoseFits, rule: PoseRule = POSE_RULE) -> PoseChoice | None:
    """ICP's pose was chosen (``choice.source`` FITTED) and the answer from it is in doubt (the
    caller's test: a poor fit, a deformation the data do not support, or a turn the pose alone
    does not confirm, ``PoseChoice.unconfirmed_turn``): the given pose replaces it when the
    deformable fit with the given pose held leaves the data within ``rule.given_ratio`` of the
    residual at ICP's pose (pooled RMS, mm), or when the turn is unconfirmed. On a partial scan of a
    dented surface the deformable model fits the data about as well tens of millimetres away as
    where they are: a move the fit does not pay for is a guess of the multi-start search, not a
    measurement; and a scan of a lobe that swung away fits the undeformed organ best turned as
    far as the lobe, a turn no tracker's registration needs. Returns the new choice, or None to
    keep ICP's: its move is then earned by the fit, and no line says its pose is in doubt (the
    line of the doubt that asked, a poor fit or the cross-validation's, stands)."""
    if choice.source is not PoseSource.FITTED:
        return None
    if fits.given_rms_mm <= rule.given_ratio * fits.fitted_rms_mm:
        return compared(choice, fits, PoseSource.GIVEN_FITS)
    # a turn the pose alone makes good (most data on the undeformed model there) is a tracker
    # that was that far off, and the data say so
    if choice.unconfirmed_turn(rule):
        return compared(choice, fits, PoseSource.GIVEN_TURN)
    return None


def with_turn(choice: PoseChoice, pose: RigidResult) -> PoseChoice:
    """``choice`` with ICP's final ``pose``'s turn from the given one recorded (FITTED only)."""
    return replace(choice, turn_deg=turn_deg(pose)) if choice.source is PoseSource.FITTED else choice


def compared(choice: PoseChoice, fits: PoseFits, source: PoseSource = PoseSource.FITTED) -> PoseChoice:
    """``choice`` with the two fits recorded (``prefer_given``), its pose from ``source``: ICP's
    kept (the default: the fit earned its move) or the given one."""
    return replace(choice, source=source, fits=fits)


@dataclass
class Determinacy:
    """How well the surface data fix the six pose parameters.

    ``eigenvalues`` (6,) of the scaled normal matrix, largest first; ``weak`` the motions
    with an eigenvalue below ``WEAK_RATIO`` × the largest, each as (rotation axis or None,
    translation direction or None, relative eigenvalue)."""
    eigenvalues: np.ndarray
    weak: list = field(default_factory=list)
    points: int = 0

    @property
    def condition(self) -> float:
        return float(self.eigenvalues[0] / self.eigenvalues[-1]) if self.eigenvalues[-1] > 0 else float("inf")

    @property
    def warning(self) -> str | None:
        if not self.weak:
            return None
        parts = []
        for rot, tr, _ in self.weak:
            if rot is not None:
                parts.append("a rotation about " + _axis_words(rot))
            else:
                parts.append("a slide along " + _axis_words(tr))
        return (f"the pose is not determined by the data: {' and '.join(parts)} leaves every surface distance "
                "unchanged (the data cover too little or too regular a surface) — add data elsewhere")

    def as_dict(self) -> dict:
        return {"condition": self.condition, "points": self.points,
                "weak_motions": [{"rotation_axis": None if r is None else np.round(r, 3).tolist(),
                                  "translation": None if t is None else np.round(t, 3).tolist(),
                                  "relative_eigenvalue": float(v)} for r, t, v in self.weak],
                "warning": self.warning}


def _axis_words(v) -> str:
    names = ("left–right", "anterior–posterior", "superior–inferior")
    v = np.asarray(v, float)
    i = int(np.argmax(np.abs(v)))
    return names[i] + (" axis" if abs(v[i]) > 0.9 else f" axis (tilted, {np.round(v, 2).tolist()})")


def pose_determinacy(model: RegistrationModel, data: dict, pose: RigidResult) -> Determinacy | None:
    """The data's sliding directions at ``pose`` (module doc); None without surface data."""
    # a warm re-registration per ultrasound frame asks again with the same pose and the same
    # stylus data (frames add iUS features, which this does not use): the last answer is kept
    # on the model and given again when pose and surface data are equal, element for element
    surface = {n: np.array(y, float) for n, y in data.items() if n in RIGID and len(y)}
    last = model.cache.determinacy
    if last is not None and np.array_equal(last[0], pose.R) and np.array_equal(last[1], pose.t) and \
            last[2].keys() == surface.keys() and all(np.array_equal(last[2][n], y) for n, y in surface.items()):
        return _copy(last[3])
    found = _determinacy(model, data, pose)
    model.cache.determinacy = (np.array(pose.R, float), np.array(pose.t, float), surface, _copy(found))
    return found


def _copy(d: Determinacy | None) -> Determinacy | None:
    return None if d is None else Determinacy(d.eigenvalues.copy(), list(d.weak), d.points)


def _determinacy(model: RegistrationModel, data: dict, pose: RigidResult) -> Determinacy | None:
    P, _, N = _surface_points(model, data, pose)
    if len(P) < 6:
        return None
    c = P.mean(0)
    L = max(float(np.linalg.norm(P - c, axis=1).max()), 1.0)
    a = np.hstack([np.cross(P - c, N) / L, N])
    A = a.T @ a / len(P)
    lam, vec = np.linalg.eigh(A)
    lam, vec = lam[::-1], vec[:, ::-1]
    weak = []
    for i in range(6):
        rel = lam[i] / lam[0] if lam[0] > 0 else 0.0
        if rel < WEAK_RATIO:
            r, t = vec[:3, i], vec[3:, i]
            if np.linalg.norm(r) > 0.5:  # mostly a rotation (about an axis through some point)
                weak.append((r / np.linalg.norm(r), None, rel))
            else:
                weak.append((None, t / np.linalg.norm(t), rel))
    return Determinacy(lam, weak, len(P))
