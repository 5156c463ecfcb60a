"""Register a case folder end to end: mesh → basis → rigid ICP → LIBR → outputs.

Frames: the model lives in the preoperative frame; data arrive in tracker space. Rigid
ICP gives T (model → tracker); LIBR then runs on the data brought into the model frame
by T⁻¹, and every output point is mapped back to tracker space by T.

Initialisation (``RobustOptions``): ICP from several starting poses, the
distinct poses it reaches screened by a few LIBR iterations each, the lowest Ω
continued; afterwards every feature's residual is checked against its expected noise
(``quality.assess_fit``), and a poor fit first tries the other poses, then says so.
"""

import json
import math
import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import cast

import numpy as np
from scipy.spatial.transform import Rotation

from ..anatomy.caseio import Case, write_csv
from ..anatomy.meshing import MeshProvenance, cached_tetmesh
from ..anatomy.model import VESSELS
from ..anatomy.tets import TetMesh
from ..defaults import EDGE_MM, K
from ..errors import CarriedWarning, InputError
from ..features import RIGID, SALIENT
from ..fitwarning import FitWarning, WarningKind, found, texts
from ..geometry.interpolation import interpolation_matrix
from ..geometry.tre import tre_stats
from ..mechanics.basis import Basis, BasisSettings, load_or_compute_basis
from ..threads import in_threads, limit_threads
from .coverage import note_coverage
from .forces import (
    WARM_WITHOUT_FORCES,
    Answer,
    ForceChoice,
    PoseTerm,
    SurfaceForces,
    choose_deformation,
    surface_points,
)
from .libr import LibrResult, LMOptions, register_libr
from .local_modes import LocalModeOptions, LocalModes, choose_local_modes, fold_model
from .model import RegistrationModel, build_model, deform, rebased_model, usable_data
from .objective import HUBER_MM, evaluate
from .pose import (
    POSE_RULE,
    Determinacy,
    PoseChoice,
    PoseFits,
    PoseSource,
    Trimmed,
    choose_pose,
    compared,
    pose_determinacy,
    prefer_given,
    rms_on_model,
    shift_mm,
    trimmed_from_given,
    turn_deg,
    with_turn,
)
from .prior import PosePrior
from .quality import EXPECTED_NOISE_MM, FitQuality, Verdict, assess_fit
from .rigid import (
    RIGID_ROBUST,
    RIGID_WITH_POSTERIOR,
    TOL_BEFORE_LIBR,
    RigidResult,
    Start,
    after,
    basin_representatives,
    beta_pose,
    multi_start_icp,
    pose_params,
    rigid_icp,
    start_poses,
)
from .rotation import rotation
from .stages import StageClock, StageTime
from .support import (
    Block,
    HeldCheck,
    Support,
    SupportOptions,
    check_support,
    check_support_pair,
    fresh_threads,
    paired_gain,
    pooled_rms,
    verdict_rule,
    weigh_correction,
)
from .uncertainty import (
    CLINICAL_GOAL_MM,
    MAD_SD,
    OrganError,
    PoseEvidence,
    declared_spread,
    organ_error,
    organ_nodes,
    pose_evidence,
)


@dataclass
class RobustOptions:
    """How registration starts and guards itself; the defaults are what the robustness
    study chose (``results/robustness.md``; docs/decisions/registration.md, "Registration: robust
    initialisation and fit quality")."""
    multi_start: bool = True  # False: one exact point-to-point ICP from the tracker pose
    start_angle_deg: float = 15.0  # starts at ± this about each axis through the data centroid
    principal_axes: bool = True  # add a principal-axes start
    icp: str = "plane"  # "plane" | "point" (multi-start ICP)
    rigid_posterior: bool = False  # iUS posterior-surface points join the rigid fit
    screen_iterations: int = 2  # LIBR iterations per distinct pose before choosing by Ω
    max_candidates: int = 3  # distinct poses screened (lowest rigid RMS first)
    huber_salient_mm: float | None = 1.0  # Huber δ (mm) on falciform and ridge residuals; None: least squares
    rigid_robust: float | None = RIGID_ROBUST  # Huber on salient points in ICP, δ = this × their median residual
    retry_poor_fit: bool = True  # a flagged fit is rerun from the other screened poses
    # continuation: first fit with the strain-energy weight × this (a stiffer organ that
    # can only move rigidly and smoothly), then relax to the true weight from there; None: off
    stiff_first: float | None = 3.0
    # the given (tracker) pose is kept when a trimmed fit from it hardly moves the data, the
    # trimmed fit's pose when most data lie on the model there (``pose.choose_pose``); a kept
    # pose is kept by LIBR too (τ, θ fixed): docs/decisions/local-loads.md, "Local loads"
    keep_given_pose: bool = True
    # spatial cross-validation of the deformation against the rigid answer; None: off
    support: SupportOptions | None = field(default_factory=SupportOptions)
    # Kelvin modes under the surface data the first fit leaves off, kept where held-out data
    # gain (``local_modes``); None: off (not yet the default: docs/decisions/local-loads.md, "Local modes
    # in register")
    local_modes: LocalModeOptions | None = None

    @classmethod
    def single_icp(cls) -> "RobustOptions":
        """One exact point-to-point ICP from the tracker pose, least squares, no guards: the
        baseline the robustness study measures the rest against (bit for bit the
        registration of commit 33e84cd)."""
        return cls(multi_start=False, icp="point", screen_iterations=0, huber_salient_mm=None, retry_poor_fit=False,
                   rigid_robust=None, stiff_first=None, keep_given_pose=False, support=None)

    @classmethod
    def multistart_only(cls) -> "RobustOptions":
        """Multi-start ICP, the Ω screen and Huber on the salient features in LIBR, without
        the robust ICP, the continuation or the guards against local loads."""
        return cls(rigid_robust=None, stiff_first=None, keep_given_pose=False, support=None)

    @classmethod
    def unguarded(cls) -> "RobustOptions":
        """The default without the guards against local loads: no kept pose, no cross-validation."""
        return cls(keep_given_pose=False, support=None)


# the registration variants the robustness study compares; the rows of
# results/robustness.csv were written under older names ("before", "after", "first-after",
# "after-no-continuation", "after-plain-icp"), rewritten once by notes/scripts/rename_robustness_methods.py
METHODS = {
    "single-icp": RobustOptions.single_icp,
    "default": RobustOptions,
    "unguarded": RobustOptions.unguarded,
    "multistart": RobustOptions.multistart_only,
    "default-no-continuation": lambda: RobustOptions(stiff_first=None),
    "default-plain-icp": lambda: RobustOptions(rigid_robust=None),
    # variants measured on older meshes before the robust ICP and the continuation joined the
    # default (docs/decisions/registration.md); they keep the guards against local loads, "multistart" does not
    "multistart-LS": lambda: RobustOptions(huber_salient_mm=None, rigid_robust=None, stiff_first=None),
    "multistart-point": lambda: RobustOptions(icp="point", rigid_robust=None, stiff_first=None),
    "multistart-posterior": lambda: RobustOptions(rigid_posterior=True, rigid_robust=None, stiff_first=None),
    "multistart-continuation-10x": lambda: RobustOptions(stiff_first=10.0, rigid_robust=None),
}


CARRIED_CHECKS = (WarningKind.ORGAN_ERROR,)
"""The checks whose lines a warm re-registration or a live frame carries from the fresh
registration it continues from (``Registration.carry``): it repeats neither the predicted error
over the organ nor the cross-validation (whose verdicts the viewer carries per target)."""
POSE_ALONE = (WarningKind.UNSUPPORTED, WarningKind.POSE_EVIDENCE, WarningKind.SURFACE_FORCES)
"""The checks whose line says why an answer is its pose alone (``Registration.why_pose_alone``)."""


@dataclass
class Registration:
    """The result of ``register``.

    Attributes
    ----------
    model : RegistrationModel
        the model that was fitted (preoperative frame).
    rigid : RigidResult
        T, model frame → tracker space (``rigid.apply``), from the rigid ICP.
    libr : LibrResult or None
        the LIBR fit: ``beta`` (3k + 6,) = (α, τ, θ) of eq. 8 in the model frame, Ω (eq. 7),
        iterations, stop reason; None for a rigid-only registration.
    data_model_frame : dict
        feature → (N, 3) mm, the data brought into the model frame by T⁻¹.
    seconds, starts, quality :
        timings per stage; the multi-start ICP's starts; the fit-quality check.
    """

    model: RegistrationModel
    rigid: RigidResult
    libr: LibrResult | None
    data_model_frame: dict
    seconds: dict = field(default_factory=dict)
    starts: list[Start] = field(default_factory=list)  # the multi-start ICP's starts (empty: single ICP)
    quality: FitQuality | None = None  # residuals against expected noise (deformable fits); .warning for the user
    pose_choice: PoseChoice | None = None  # given, trimmed-fit or ICP's pose (``pose.choose_pose``)
    determinacy: Determinacy | None = None  # the pose's sliding directions (``pose.pose_determinacy``)
    support: Support | None = None  # the deformation's held-out prediction against rigid (``support``)
    # warnings raised before the fit (too few points) and about its data (too little coverage)
    notes: list[FitWarning] = field(default_factory=list)
    # the deformable answer's predicted error over the organ against the oncological margin
    # (``uncertainty.organ_error``); fresh deformable answers only
    organ: OrganError | None = None
    # the local-mode step (``RobustOptions.local_modes``): where its sources went, the held-out
    # RMS with and without them, and whether ``model`` carries them
    local_modes: LocalModes | None = None
    # the declared pose knowledge the fit used (``register(pose_prior=)``), centred on ``rigid``
    pose_prior: PosePrior | None = None
    # with a declared pose and no supported deformation: the fitted pose against the given one,
    # and the shown pose's predicted error (``uncertainty.PoseEvidence``); its line replaces the
    # cross-validation's and the deformable fit's quality, neither of which is the answer shown
    pose_evidence: PoseEvidence | None = None
    # ``register(surface_forces=True)``: no deformation, the basis's fit or surface forces,
    # whichever predicts held-out surface data best (``forces.choose_deformation``); it decides
    # the answer in place of ``support``
    forces: ForceChoice | None = None
    # ``register(surface_forces=True)`` warm (``beta0``): the forces are not refitted (one solve
    # per force site is no live update), so the basis's answer is shown and a line says so
    warm_without_forces: bool = False
    # a model held at declared supports, fresh and guarded: its answer against the free-floating
    # basis on the same held-out blocks (``support.HeldCheck``); contradicted, the registration
    # returned is the free-floating model's, carrying this check and its line
    held: HeldCheck | None = None
    # wall and CPU seconds per stage, in the order run (``stages``): every guard's cost apart
    stages: dict[str, StageTime] = field(default_factory=dict)
    # the lines of checks this answer did not repeat, carried from the fresh registration it
    # continues from (``carry``): a warm start's or a live frame's, said in ``warnings``
    carried: list[FitWarning] = field(default_factory=list)

    @property
    def deformed(self) -> bool:
        """True when the answer is the deformable fit; False when it is the rigid pose alone:
        no LIBR, or a deformation the data do not support *and* a kept pose (given, or the
        trimmed fit's: most data lay on the undeformed model there, so it is a known-good
        answer). ICP's fitted pose is no such baseline: an unsupported deformation from it
        stays the answer, with its warning (on the study cases it was the better one)."""
        if self.forces is not None:
            return self.forces.answer is not Answer.NONE
        if self.libr is None:
            return False
        return self.support is None or self.support.supported or not self.rigid.kept

    @property
    def warnings(self) -> list[FitWarning]:
        """Every warning about this answer, in the order said (the CLI, result.json, the viewer
        and Slicer show them): the one rule for which checks stand for the answer shown."""
        lines = list(self.notes)
        if self.pose_evidence is not None and not self.deformed:
            return lines + found(WarningKind.POSE_EVIDENCE, self.pose_evidence.warning)
        doubt = bool(lines) or (self.determinacy is not None and self.determinacy.warning is not None)
        return lines + [w for kind, text in (
            (WarningKind.POSE_SEARCH, self.pose_choice.warning if self.pose_choice else None),
            (WarningKind.UNDETERMINED_POSE, self.determinacy.warning if self.determinacy else None),
            (WarningKind.UNSUPPORTED, self.support.warning_for(
                shown_rigid=not self.deformed, given=self.pose_choice is None or self.pose_choice.given,
                declared=self.pose_prior is not None) if self.support and self.forces is None else None),
            (WarningKind.SURFACE_FORCES, self.forces.warning if self.forces is not None else None),
            (WarningKind.SUPPORTS, self.forces.supports_warning if self.forces is not None else None),
            (WarningKind.SUPPORTS, self.held.warning if self.held is not None else None),
            (WarningKind.SURFACE_FORCES, WARM_WITHOUT_FORCES if self.warm_without_forces else None),
            (WarningKind.POOR_FIT, self.quality.warning if self.quality else None),
            # no organ figure beside a pose not to be believed (the notes, an undetermined
            # pose): the estimate's calibration says nothing at a pose 100 mm off (the demo's
            # 40-point patch: 535 mm predicted, 35 true); the pose's own line says what to do
            (WarningKind.ORGAN_ERROR,
             self.organ.warning if self.organ is not None and self.deformed and not doubt else None))
            for w in found(kind, text)] + (self.carried if self.deformed and not doubt else [])

    def carry(self, checked: "Registration | None", said: str) -> None:
        """Carry the lines of the checks a warm re-registration does not repeat (``CARRIED_CHECKS``: the
        predicted error over the organ) from ``checked``, the fresh registration it continues
        from, as ``checked.warnings`` said them, each followed by `` (said)`` (the caller's words
        for "at the last full registration") and marked ``carried``. Nothing for a registration
        that made the check itself (``checked`` is it, or it has its own ``organ``) or whose
        answer is not deformed. ``warnings`` then says them under its own rule: not beside a
        pose not to be believed (docs/decisions/live.md, "A warm start keeps the last fresh
        fit's checks, said to be from then")."""
        if checked is None or checked is self or self.organ is not None or not self.deformed:
            self.carried = []
            return
        self.carried = [FitWarning(w.kind, f"{w.text} ({said})", carried=True)
                        for w in checked.warnings if w.kind in CARRIED_CHECKS and not w.carried]

    @property
    def why_pose_alone(self) -> FitWarning | None:
        """The line of ``warnings`` that says why the answer shown is the pose alone, without
        deformation (the deformation not supported or not determined by the data, a declared
        pose's evidence, the surface forces' choice); None for a deformed answer, and for a pose
        alone that no line stands for (a declared pose the data confirm, shown without a line:
        docs/decisions/registration.md, "A declared rigid move judged at the scale of the misfit
        it leaves"). The viewer writes its head beside each target, which has no predicted error."""
        if self.deformed:
            return None
        return next((w for w in self.warnings if w.kind in POSE_ALONE), None)

    @property
    def pose_doubts(self) -> list[FitWarning]:
        """Everything that says this answer's pose is not to be believed (empty: nothing), each
        once: the notes (too few or collinear points, ``undetermined_pose``; too little coverage,
        which ``register`` notes on every registration it returns, and a restored result carries
        in its saved line) and an undetermined pose; with either, the pose search's own line (ICP
        turned the organ further than a tracker errs), which belongs beside it: said once, pinned
        over the viewer's 3D view, not in a second red box."""
        lines = list(self.notes)
        if self.determinacy is not None:
            lines += found(WarningKind.UNDETERMINED_POSE, self.determinacy.warning)
        if lines and self.pose_choice is not None:
            lines += found(WarningKind.POSE_SEARCH, self.pose_choice.warning)
        return list(dict.fromkeys(lines))

    @property
    def fit_warnings(self) -> list[FitWarning]:
        """The fit's own warnings, the only ones a method without the pose and deformation
        checks has: the notes (too few points, too little coverage) and a poor fit."""
        return list(self.notes) + found(WarningKind.POOR_FIT, self.quality.warning if self.quality else None)

    def transform(self, points, beta=None, B=None) -> np.ndarray:
        """Preoperative points (P, 3) mm → registered positions in tracker space (P, 3) mm:
        T(x(β)), eq. 8 then the rigid ICP's T (the rigid pose alone when the deformation is
        not supported, ``deformed``). ``beta``: another state than the fit's;
        ``B``: the points' interpolation matrix (``interpolation_matrix``), when the caller
        transforms the same points many times (locating them in the mesh dominates)."""
        points = np.asarray(points, float)
        if beta is None and self.forces is not None and self.forces.answer is Answer.FORCES:
            assert self.forces.u is not None
            basis = self.model.basis
            B = interpolation_matrix(basis.nodes, basis.tets, points) if B is None else B
            moved = points + B @ self.forces.u
            if self.forces.pose is not None:  # the forces' own rigid part, fitted with them (eq. 8)
                moved = beta_pose(self.forces.pose, self.model.centroid).apply(moved)
            return self.rigid.apply(moved)
        b = self.libr.beta if (beta is None and self.deformed and self.libr is not None) else beta
        basis = self.model.basis
        if b is None:
            return self.rigid.apply(points)
        return self.rigid.apply(deform_points(basis, self.model.centroid, b, points, B))


def deform_points(basis: Basis, centroid, beta, points, B=None) -> np.ndarray:
    """x(β) of eq. 8 for arbitrary preoperative points, displacement interpolated in the mesh.

    Parameters
    ----------
    basis : Basis
        J_u (3M, 3k) on the mesh's M nodes.
    centroid : (3,) mm
        x̄0 (``RegistrationModel.centroid``).
    beta : (3k + 6,)
        (α, τ, θ); τ mm, θ radians.
    points : (P, 3) mm
        preoperative positions inside (or near) the mesh.
    B : sparse (P, M), optional
        their interpolation matrix, when already computed.

    Returns
    -------
    (P, 3) mm, in the model frame (``Registration.transform`` adds the rigid T).
    """
    n = basis.Ju.shape[1]
    B = interpolation_matrix(basis.nodes, basis.tets, points) if B is None else B
    with limit_threads(1):  # see ``uncertainty.node_positions``
        u = (basis.Ju @ beta[:n]).reshape(-1, 3)
    return deform(np.asarray(points, float), B @ u, beta, centroid)[1]


def prepare(case: Case, edge=EDGE_MM, k=K, cache_root=None, supports: str | None = None,
            release: str = "N", stiffness: float | None = None, points: tuple = ()) -> tuple[RegistrationModel, dict]:
    """Mesh, basis and registration model of a case, each cached by content.

    Parameters
    ----------
    case : Case
        from ``read_case`` (its preoperative liver, vessels, regions and fiducials are used).
    edge : float
        target tet edge length, mm (default ``defaults.EDGE_MM``).
    k : int
        number of control points; the basis J_u has 3k modes (paper eq. 3–5, default
        ``defaults.K``).
    cache_root : Path, optional
        cache folder (default ``$NAVAPP_CACHE`` or ``~/.cache/navapp``).
    supports, release : str, optional
        where the organ is held (``mechanics.supports.Supports``: ligaments, posterior,
        bare_area; ``release`` L, N or R for the ligaments): every mode of the basis vanishes
        there, so the organ moves only as its supports let it, and the rigid parameters are
        the tracker's. None: the paper's free-floating basis. ``points``: with
        ``supports="points"``, the support points ((x, y, z), …) mm (a case's preop/supports.csv).
    stiffness : float, optional
        Pa/mm: the supports hold on springs this stiff (every mode moves there elastically);
        None: held firmly (zero displacement).

    Returns
    -------
    model : RegistrationModel
        every model feature carried by the mesh (B·J_u per point, eq. 8).
    seconds : dict
        ``mesh``, ``basis``, ``model``: wall time of each stage (a cache hit is fast).
    """
    basis, report, sec = mesh_and_basis(case.preop.liver, edge, k, cache_root, supports, release, stiffness, points)
    t = time.perf_counter()
    model = build_model(basis, case.preop, case.preop.fiducials)
    model.mesher = MeshProvenance.from_report(report)
    sec["model"] = time.perf_counter() - t
    return model, sec


def mesh_and_basis(liver, edge=EDGE_MM, k=K, cache_root=None, supports: str | None = None,
                   release: str = "N", stiffness: float | None = None,
                   points: tuple = ()) -> tuple[Basis, dict, dict]:
    """``prepare``'s first two stages: the tetrahedral mesh of ``liver`` (a closed surface,
    mm) and its deformation basis, each cached by content. Needs the preoperative liver only,
    so a viewer makes it ahead while its scene is simulated. Returns the basis, the mesher's
    report and the wall seconds of ``mesh`` and ``basis``."""
    sec = {}
    t = time.perf_counter()
    mesh, report = cached_tetmesh(liver, edge, cache_root)
    sec["mesh"] = time.perf_counter() - t
    t = time.perf_counter()
    if k > len(np.unique(mesh.boundary_faces())):
        raise InputError(f"--k {k} is more control points than the mesh has surface nodes "
                         f"({len(np.unique(mesh.boundary_faces()))} at {edge:g} mm): use a smaller k or a finer edge")
    basis, _ = load_or_compute_basis(mesh, BasisSettings(k=k, supports=supports, release=release,
                                                         stiffness=stiffness, points=tuple(points)),
                                     cache_root=cache_root)
    sec["basis"] = time.perf_counter() - t
    return basis, report, sec


# data this many times smaller than the model: metres read as millimetres (a 250 mm organ's
# data then span ≤ 0.25 mm); no real stylus or iUS set of ≥ 4 points is that small
UNIT_RATIO = 500.0


MIN_SURFACE_POINTS = 6  # one point-to-surface distance per point, six pose parameters
COLLINEAR = 0.02  # second singular value of the centred points below this × the first: a line


def undetermined_pose(data: dict) -> str | None:
    """One line when the data cannot fix the rigid pose (hard cases "few", "collinear",
    "k >> data": registered silently before, TRE 50–140 mm): fewer than six points, or
    points on one line (the rotation about it leaves every residual unchanged); three or
    more fiducials off a line fix it on their own. None when the pose is determined."""
    def spread(p):
        return np.linalg.svd(p - p.mean(0), compute_uv=False) if len(p) > 1 else np.zeros(3)

    fid = data.get("fiducials")
    if fid is not None and len(fid) >= 3 and spread(fid)[1] > COLLINEAR * spread(fid)[0]:
        return None
    pts = np.vstack(list(data.values())) if data else np.zeros((0, 3))
    if not len(pts):
        return None
    if len(pts) < MIN_SURFACE_POINTS:
        return (f"only {len(pts)} data points: the rigid pose needs at least {MIN_SURFACE_POINTS} and is not "
                "determined — the result may be far off; add data")
    s = spread(pts)
    if s[1] <= COLLINEAR * s[0]:
        return (f"the {len(pts)} data points lie on one line: the rotation about it is not determined — the "
                "result may be far off; add data off that line")
    return None


def check_units(model: RegistrationModel, data: dict) -> None:
    """Refuse data whose extent is a tiny fraction of the model's (hard case "metres as
    mm": registered silently before, to a meaningless pose)."""
    pts = [p for p in data.values() if len(p)]
    if not pts or sum(len(p) for p in pts) < 4:
        return
    span = float(np.ptp(np.vstack(pts), axis=0).max())
    # the model's extent once, not per live update (keyed by the nodes: a replaced model shares the cache)
    hit = model.cache.extent_mm
    if hit is None or hit[0] is not model.basis.nodes:
        hit = model.cache.extent_mm = (model.basis.nodes, float(np.ptp(model.basis.nodes, axis=0).max()))
    size = hit[1]
    if span < size / UNIT_RATIO:
        raise InputError(f"the data points span {span:.3g} mm against a {size:.0f} mm model: are they in metres? "
                         "navapp reads coordinates in millimetres")


def _given(rms_mm: float = 0.0) -> RigidResult:
    """The tracker's own pose (identity: the data taken as already in the model frame), kept."""
    return RigidResult(np.eye(3), np.zeros(3), 0, rms_mm, kept=True)


def _settings(options: LMOptions | None, init: RobustOptions | None) -> tuple[LMOptions, RobustOptions]:
    options = options or LMOptions()
    init = init or RobustOptions()
    if init.huber_salient_mm and not options.weights.huber_mm:
        options = replace(options, weights=replace(options.weights, huber_mm={
            n: init.huber_salient_mm for n in SALIENT}))
    return options, init


def _rigid_features(init: RobustOptions) -> tuple[str, ...]:
    return RIGID_WITH_POSTERIOR if init.rigid_posterior else RIGID


def _multi_start(model: RegistrationModel, data: dict, options: LMOptions, init: RobustOptions) -> list[Start]:
    features = _rigid_features(init)
    poses = start_poses(model, {k: v for k, v in data.items() if k in features} or data,
                        init.start_angle_deg, init.principal_axes)
    return multi_start_icp(model, data, poses, options.weights, mode=init.icp, features=features,
                           robust=init.rigid_robust)


def rigid_starts(model: RegistrationModel, data: dict, options: LMOptions | None = None,
                 init: RobustOptions | None = None) -> list[Start]:
    """The multi-start ICP of ``register``'s rigid stage, to share between registrations
    whose rigid features (``RobustOptions.rigid_posterior``: the stylus's, or also the iUS
    posterior wall) are the same; pass it as ``register(..., starts=...)``.

    Parameters
    ----------
    model : RegistrationModel
    data : dict
        feature → (N, 3) points, mm, tracker space; only the rigid features are used.
    options, init :
        as for ``register``.

    Returns
    -------
    list of Start
        every starting pose and where its ICP ended.
    """
    options, init = _settings(options, init)
    return _multi_start(model, usable_data(model, data), options, init)


def _cross_validate(model: RegistrationModel, local: dict, options: LMOptions, settings: SupportOptions, cancel,
                    rigid: RigidResult, result: LibrResult, support: Support | None = None,
                    local_modes: bool = False, declared: bool = False, paired: bool = False,
                    beside: Callable[[], None] | None = None) -> Support | None:
    """The spatial cross-validation of a fresh deformable fit (``support``: already made, by
    the local-mode step's folds); from a kept pose (a known-good answer without deformation),
    or where the cross-validation fails from ICP's pose (whether to warn, ``Support.outweighs``),
    the correction is also weighed against its own σ. So is a fit with local modes
    (``local_modes``) from ICP's pose: the modes were placed where the data asked, and
    held-out blocks are a weaker judge of a fit that can bend there (docs/decisions/local-loads.md,
    "Local modes in register"). With a declared pose (``declared``) the held-out prediction is the
    one criterion: the correction is not weighed against its σ (docs/decisions/registration.md, "Pose prior");
    with ``paired`` (a declared pose within the clinical goal) surface data alone are judged by one
    paired standard error of the held-out gain, not the 30 % margin (``SupportOptions.surface_se``)."""
    if support is None and not local_modes:  # with local modes only the folds' own verdict, which no block saw
        support = check_support(model, local, options, replace(settings, surface_se=True) if paired else settings,
                                cancel, beside=beside)
    if support is not None and not declared and (rigid.kept or not support.predicts or local_modes) and \
            not (cancel is not None and cancel.is_set()):
        support = weigh_correction(model, local, result.beta, support, options, settings)
    return support


SCALE_ROUNDS = 6  # refits of the rigid stage while its scale σ_F settles (``_declared_rigid``)


def _declared_rigid(model: RegistrationModel, data: dict, prior: PosePrior, options: LMOptions,
                    init: RobustOptions, cancel) -> tuple[RigidResult, PosePrior, list[Start]]:
    """The rigid stage with a declared pose (docs/design.md, "Pose prior").

    τ, θ are fitted by LM with the prior about the given pose (identity: the data arrive in
    the preoperative frame), with Huber weights on every feature. The search is confined to
    where the prior allows: the multi-start ICP from the given pose and from turns of at most
    two declared σ_θ (no principal-axes flip), its distinct poses kept within ``PRIOR_REACH``
    declared σ of the given one. Each kept pose, and the given one, starts an LM fit; the one
    with the lowest Ω (data and prior, at one scale) is the answer. Its scale σ_F is the robust
    standard deviation of the data's distances from the undeformed model there (``prior``, "The
    scale"), refitted until it changes by less than a tenth, floored at the features' expected
    noise. Returns the pose
    (model → data frame), the prior re-centred on where the given pose is from it, and the
    starts searched."""
    n = model.basis.Ju.shape[1]
    floor = _noise_floor(data)
    # Huber on every feature (δ = ``HUBER_MM``): where the organ deformed under part of the data
    # (a dent), a rigid fit in least squares shares that misfit out as a pose error; with the
    # pull of the points far off bounded, the prior holds the given pose unless most data move
    huber = {name: HUBER_MM for name in data}
    rigid_only = replace(options, deform=False, pose=True)
    at_given = replace(prior, centre=(0.0,) * 6)
    c = model.centroid

    def beta_of(pose: RigidResult) -> np.ndarray:
        b = np.zeros(n + 6)
        b[n:] = pose_params(pose, c)
        return b

    def fit(beta0, current, rounds=SCALE_ROUNDS):
        fitted = None
        for _ in range(rounds):
            fitted = register_libr(model, data, beta0, replace(rigid_only, weights=replace(
                options.weights, huber_mm=huber, pose_prior=current)), None, cancel)
            sd = max(_robust_sd(model, data, fitted.beta, options.weights), floor)
            settled = abs(sd - current.feature_sd_mm) < 0.1 * current.feature_sd_mm
            current = replace(current, feature_sd_mm=sd)
            if settled or fitted.stop_reason == "cancelled":
                break
        assert fitted is not None
        return fitted, current

    best, current = fit(None, at_given)
    starts: list[Start] = []
    if init.multi_start and any(n_ in RIGID for n_ in data):
        features = _rigid_features(init)
        turn = min(init.start_angle_deg, 2.0 * prior.sd_deg)
        poses = start_poses(model, {k: v for k, v in data.items() if k in features} or data, turn, False)
        starts = multi_start_icp(model, data, poses, options.weights, mode=init.icp, features=features,
                                 robust=init.rigid_robust)
        scale = current  # every candidate's Ω at the given pose's scale: one criterion to compare
        here = fit(best.beta, scale, rounds=1)[0].omega
        for rep in basin_representatives(starts)[:init.max_candidates]:
            b = beta_of(rep.fitted)
            reach = np.concatenate([b[n:n + 3] / prior.sd_mm, b[n + 3:] / prior.sd_rad])
            if np.abs(reach).max() > PRIOR_REACH or np.allclose(b, 0.0):
                continue
            other, _ = fit(b, scale, rounds=1)
            if other.omega < here:
                here = other.omega
                best, current = fit(other.beta, scale)
                for st in starts:
                    st.chosen = st is rep
    beta = best.beta
    # the pose moved from the given one (model → data frame)
    pose = replace(beta_pose(beta, c), iterations=best.iterations)
    pose = replace(pose, rms_mm=rms_on_model(model, data, pose))
    return pose, _given_from(current, pose, beta[n:]), starts


def _given_from(prior: PosePrior, moved: RigidResult, params: np.ndarray) -> PosePrior:
    """``prior`` re-centred on where the given pose lies from ``moved`` (the pose moved from the
    given one, model → data frame; ``params``: its τ, θ (6,), ``rigid.pose_params``)."""
    return replace(prior, centre=tuple(np.concatenate([-moved.R.T @ params[:3], -params[3:]]).tolist()))


def _noise_floor(data: dict) -> float:
    """The least expected noise (mm) of the features present: the floor of the prior's scale σ_F."""
    return min(EXPECTED_NOISE_MM.get(name, 1.0) for name in data)


def _robust_sd(model: RegistrationModel, data: dict, beta, weights) -> float:
    """σ_F of the prior's scale at β (``prior``, "The scale"): the data's residuals' robust
    standard deviation, 1.4826 × their median absolute value (the normal's MAD factor), so a
    deformation under fewer than half of the points does not set it."""
    ev = evaluate(model, data, beta, replace(weights, pose_prior=None), jacobian=False)
    return float(MAD_SD * np.median(np.abs(ev.f[:-1]))) if len(ev.f) > 1 else 0.0


def _settle_scale(model: RegistrationModel, local: dict, result, options: LMOptions, cancel):
    """The deformable fit with the pose prior's scale σ_F re-estimated from its own residuals.

    σ_F is the noise of the likelihood the prior is weighed against (``prior``, "The scale").
    The rigid stage estimates it at the undeformed model, where the deformation is still part
    of the misfit; once LIBR has fitted the deformation, what is left is the residual the
    model cannot explain, and that is the likelihood's noise. So σ_F is re-estimated from the
    answer's residuals (robust σ, floored at the features' expected noise) and the fit is
    continued from its β until σ_F changes by less than a tenth (at most ``SCALE_ROUNDS``):
    the scale and the answer agree, as in an EM estimate of a noise variance. Kept with the
    rigid stage's scale, a declared tracker offset of its true size was held part-way
    (tool2-e at S: 10.6 mm against 7.05 mm settled; docs/decisions/registration.md, "Pose prior")."""
    prior = options.weights.pose_prior
    assert prior is not None
    floor = _noise_floor(local)
    for _ in range(SCALE_ROUNDS):
        sd = max(_robust_sd(model, local, result.beta, options.weights), floor)
        if abs(sd - prior.feature_sd_mm) < 0.1 * prior.feature_sd_mm:
            break
        prior = replace(prior, feature_sd_mm=sd)
        options = replace(options, weights=replace(options.weights, pose_prior=prior))
        result = register_libr(model, local, result.beta, options, None, cancel)
        if result.stop_reason == "cancelled":
            break
    return result, options


def _rigid_at_settled_scale(model: RegistrationModel, data: dict, options: LMOptions, cancel, moved: RigidResult,
                            rigid: RigidResult, result: LibrResult
                            ) -> tuple[RigidResult, RigidResult, dict, PosePrior, LibrResult] | None:
    """The declared rigid answer where the deformation is not supported and the pose is declared
    wider than the clinical goal: τ, θ refitted to all the data (α = 0) with the prior at the
    deformable answer's settled scale σ_F (``options``, after ``_settle_scale``), from the rigid
    stage's pose.

    The rigid model is the deformable one with α held at zero, and the two are compared by the
    held-out blocks at that scale: each fold's rigid answer is this fit on its training data
    (``support``). The noise of a nested comparison is read from the larger model's residuals
    (as Mallows' C_p and the F-test read it); the rigid stage's own scale, at the undeformed
    model, also counts the misfit of the offset it has not yet removed, and held a tracker
    offset declared at its true size near the given pose (tooldraw4_2-e at S: 17.2 mm shown,
    3.18 refitted; docs/decisions/registration.md, "The declared rigid answer at the settled
    scale"). So the pose shown is the one the cross-validation judged. Within the goal the given
    pose is the reference and the rigid stage's pose is judged against it as before: refitted
    there too, two pre-aligned answers went silently worse (same section).

    Returns ``(moved, rigid, local, centred, result)``: the pose relative to the given one, the
    pose (model → tracker frame), the data in its model frame, the prior centred on where the
    given pose lies from it at the settled scale (for ``PoseEvidence`` and the answer's options),
    and the deformable fit re-expressed in that frame (its β and ``local`` stay one pair); None
    when the refit was cancelled."""
    settled = options.weights.pose_prior
    assert settled is not None
    local = {name: rigid.inverse(p) for name, p in data.items()}
    fitted = register_libr(model, local, None, replace(options, deform=False, pose=True), None, cancel)
    if fitted.stop_reason == "cancelled":
        return None
    step = beta_pose(fitted.beta, model.centroid)
    moved = replace(after(moved, step), iterations=moved.iterations + fitted.iterations, kept=moved.kept)
    rigid = replace(after(rigid, step), iterations=moved.iterations, kept=rigid.kept)
    rigid = replace(rigid, rms_mm=rms_on_model(model, data, rigid))
    local = {name: rigid.inverse(p) for name, p in data.items()}
    centred = _given_from(settled, moved, pose_params(moved, model.centroid))
    back = RigidResult(step.R.T, -step.R.T @ step.t, 0, 0.0)
    return moved, rigid, local, centred, replace(result, beta=_rebased(model, result.beta, back))


def _rebased(model: RegistrationModel, beta: np.ndarray, pose: RigidResult) -> np.ndarray:
    """β (3k + 6,) fitted to data in ``pose``'s model frame, re-expressed about the given pose
    (identity): the same deformed organ in the tracker frame. With x(β) = R(θ)(x0 + u − x̄0) + τ + x̄0
    (eq. 8) and the pose y ↦ R_p y + t_p: R(θ') = R_p R(θ), τ' = R_p (τ + x̄0) + t_p − x̄0."""
    n = model.basis.Ju.shape[1]
    out = np.array(beta, float)
    c = model.centroid
    out[n:n + 3] = pose.R @ (beta[n:n + 3] + c) + pose.t - c
    out[n + 3:] = Rotation.from_matrix(pose.R @ rotation(beta[n + 3:])).as_euler("XYZ")
    return out


def free_model(model: RegistrationModel, cache_root=None) -> RegistrationModel:
    """The free-floating model of a model held at declared supports: the same mesh, features and
    k, the basis without supports (from the basis cache; computed and cached when absent)."""
    return held_model(model, None, model.basis.settings.release, cache_root)


def held_model(model: RegistrationModel, held: str | None, release: str = "N", cache_root=None,
               stiffness: float | None = None, points: tuple = ()) -> RegistrationModel:
    """``model`` with its basis held at the declared supports ``held`` (``mechanics.supports``;
    ``release``: the ligament released; ``stiffness``: on springs, Pa/mm; ``points``: with
    ``held="points"``; None: free-floating): the same mesh, features and k, every mode vanishing
    there, or moving on the springs (from the basis cache; computed and cached when absent)."""
    basis = model.basis
    settings = replace(basis.settings, supports=held, release=release, stiffness=None if held is None else stiffness,
                       points=() if held is None else tuple(points))
    if settings == basis.settings:
        return model
    other, _ = load_or_compute_basis(TetMesh(basis.nodes, basis.tets), settings, basis.material,
                                     cache_root=cache_root)
    return rebased_model(model, other)


PRIOR_REACH = 3.0
"""How many declared standard deviations (per axis) from the given pose a multi-start ICP
pose may lie and still be a candidate of the declared rigid stage (``_declared_rigid``)."""


def register(model: RegistrationModel, data: dict, deform=True, options: LMOptions | None = None,
             callback=None, cancel=None, beta0=None, rigid: RigidResult | None = None,
             init: RobustOptions | None = None, starts: list[Start] | None = None,
             pose_prior: PosePrior | None = None, given: RigidResult | None = None,
             surface_forces: bool = False, undeclared: RegistrationModel | None = None) -> Registration:
    """Rigid initialisation then (unless ``deform`` is False) LIBR: β minimising Ω of eq. 7
    (data terms of Table I plus the strain-energy term) by Levenberg–Marquardt.

    Parameters
    ----------
    model : RegistrationModel
        from ``prepare``.
    data : dict
        feature → (N, 3) points, mm, tracker space (names: ``navapp.features.NAMES``).
    deform : bool
        False: rigid ICP only (``Registration.libr`` is None).
    options : LMOptions
        the solver's settings and the weights w_F, w_E (default ``LMOptions()``).
    callback, cancel :
        ``callback(Progress)`` after every LM iteration; setting the ``threading.Event``
        ``cancel`` stops at the next iteration with the best β so far.
    rigid, beta0 :
        warm start (e.g. after adding an iUS plane): pass the previous ``rigid`` result and
        ``beta0`` = the previous β (3k + 6,); ICP is then skipped and LM starts from β0.
    init : RobustOptions
        the initialisation and fit guards (default ``RobustOptions()``).
    pose_prior : PosePrior, optional
        what is known of the pose before the data (``prior.PosePrior``): the rigid parameters
        carry a Gaussian prior about the given pose. None: an unknown frame, searched.
    given : RigidResult, optional
        the pose ``pose_prior`` is about (model → data frame), e.g. the session's previous
        registration; default the data's own frame (identity: the data arrive in the
        preoperative frame). Ignored without ``pose_prior`` or with a warm start.
    starts : list of Start, optional
        the multi-start ICP of these data's rigid features (``rigid_starts``), computed once
        for registrations whose rigid features are the same (a study's S and S + planes
        rows share the stylus's). Everything after it — the basin screening on all the
        data, the pose rules, the cross-validation — runs here, so the answer equals one
        without ``starts``; the list is not changed.
    pose_prior : PosePrior, optional
        the declared pose knowledge (``prior``): the rigid stage fits within it.
    surface_forces : bool
        with a basis held at declared supports (``prepare(supports=)``) and a fresh deformable
        fit: the answer is no deformation, the basis's fit or a force at every surface node,
        whichever predicts held-out surface data best (``forces.choose_deformation``;
        ``Registration.forces``). Not the default: it costs one solve per force site. The
        free-floating basis's fits are held out on the same blocks beside it: where they predict
        the data better than the answer shown, the declared supports are contradicted and a
        warning says so (``ForceChoice.supports_warning``). A warm re-registration (``beta0``)
        does not refit the forces: it shows the basis's answer, with a line saying so
        (``Registration.warm_without_forces``).
    undeclared : RegistrationModel, optional
        with ``surface_forces``: the same mesh's free-floating model for that check (default
        ``free_model(model)``, the free basis from the cache).

    Returns
    -------
    Registration
        ``transform(points)`` maps preoperative points (P, 3) mm to tracker space.

    Raises
    ------
    InputError
        for data that are not (N, 3), not finite, or of an unknown feature.
    """
    reg = _register(model, data, deform, options, callback, cancel, beta0, rigid, init, starts, pose_prior, given,
                    surface_forces, undeclared)
    if reg.held is not None and reg.held.contradicted and not (cancel is not None and cancel.is_set()):
        # the data contradict the declared supports: the free-floating model's registration,
        # every check its own, with the line that says why it is the one shown (docs/decisions/local-loads.md,
        # "Declared supports tested by the data")
        free = undeclared if undeclared is not None else free_model(model)
        alt = _register(free, data, deform, options, callback, cancel, beta0, rigid, init, starts, pose_prior,
                        given, False, None)
        if alt.deformed or reg.deformed:
            alt.held = replace(reg.held, replaced=True)
            alt.seconds["held_model"] = sum(reg.seconds.values())  # the registration it replaces, its check included
            return alt
        # two rigid answers, which the supports do not shape: the held one stays, with no line
        # (on the local-load cases this halved the lines and changed no answer's TRE)
    elif reg.held is not None and reg.deformed and not reg.held.rests_on_supports and \
            not (cancel is not None and cancel.is_set()):
        # the data bear the supports out on the held-out blocks: is the change they make to the
        # answer over the organ no more than those data bear out? (``HeldCheck.beyond_data``;
        # docs/decisions/local-loads.md, "Wrong supports: the change the supports make")
        t = time.perf_counter()
        free = undeclared if undeclared is not None else free_model(model)
        with warnings.catch_warnings():  # its lines are its own answer's, which is not shown
            warnings.simplefilter("ignore")
            alt = _register(free, data, deform, options, None, cancel, beta0, rigid, init, starts, pose_prior,
                            given, False, None)
        if not (cancel is not None and cancel.is_set()):
            at = model.basis.nodes[organ_nodes(model)]
            B = interpolation_matrix(model.basis.nodes, model.basis.tets, at)
            change = float(np.sqrt(np.mean(np.sum((reg.transform(at, B=B) - alt.transform(at, B=B)) ** 2, axis=1))))
            reg.held = replace(reg.held, organ_change_mm=change)
        reg.seconds["supports_check"] = reg.seconds.get("supports_check", 0.0) + time.perf_counter() - t
    return reg


def _register(model: RegistrationModel, data: dict, deform, options: LMOptions | None, callback, cancel, beta0,
              rigid: RigidResult | None, init: RobustOptions | None, starts: list[Start] | None,
              pose_prior: PosePrior | None, given: RigidResult | None, surface_forces: bool,
              undeclared: RegistrationModel | None) -> Registration:
    """``register`` with the model as given (the answer held at declared supports is checked
    against the free-floating basis, ``Registration.held``, and not replaced here)."""
    return _Registering(model, data, deform, options, callback, cancel, beta0, rigid, init, starts, pose_prior,
                        given, surface_forces, undeclared).run()


class _Registering:
    """One registration of ``_register``, stage by stage. Each stage reads the state the ones
    before it left and updates it; ``run`` calls them in order:

    - ``rigid_stage``: the pose — the declared rigid fit, or the multi-start search, the
      screening of its basins and the undeclared pose choice;
    - ``deformable_stage``: LIBR from that pose (and, on two cores, the cross-validation's folds
      beside it), a poor fit's other basins, the local modes;
    - ``support_stage``: the cross-validation of the deformation (``Support``);
    - ``declared_answer``: with a declared pose and no supported deformation, the rigid answer
      (``PoseEvidence``);
    - ``given_pose_again``: from ICP's pose, an answer in doubt asked whether the given pose
      held fits as well;
    - then the answer's checks: the surface forces or the declared supports against the free
      basis, the organ's predicted error, the coverage line.
    """

    def __init__(self, model: RegistrationModel, data: dict, deform, options: LMOptions | None, callback, cancel,
                 beta0, rigid: RigidResult | None, init: RobustOptions | None, starts: list[Start] | None,
                 pose_prior: PosePrior | None, given: RigidResult | None, surface_forces: bool,
                 undeclared: RegistrationModel | None):
        if beta0 is not None and len(beta0) != model.basis.Ju.shape[1] + 6:
            # a warm start from a fit whose model carried local modes: its β has their weights too
            raise InputError(f"beta0 has {len(beta0)} entries; this model's state has "
                             f"{model.basis.Ju.shape[1] + 6} (a registration with local modes: pass its own reg.model)")
        if surface_forces and model.basis.settings.supports is None:
            raise InputError("surface forces need declared supports: prepare the model with supports= "
                             "(a free-floating organ has no unique displacement under a load)")
        data = usable_data(model, data)
        check_units(model, data)
        self.model, self.data, self.deform, self.callback, self.cancel = model, data, deform, callback, cancel
        self.beta0, self.given, self.surface_forces, self.undeclared = beta0, given, surface_forces, undeclared
        self.notes: list[FitWarning] = []
        if rigid is None and (why := undetermined_pose(data)):
            warnings.warn(why, CarriedWarning, stacklevel=3)
            self.notes.append(FitWarning(WarningKind.FEW_POINTS, why))
        self.warm = rigid is not None  # the pose is given: no choice of pose
        self.fresh = beta0 is None  # a deformable fit from β = 0 (not a warm re-registration): cross-validated
        options, self.init = _settings(options, init)
        self.declared = pose_prior is not None and not self.warm and bool(data)
        if pose_prior is not None and self.warm:  # about the warm start's pose (the caller's last registration)
            options = replace(options, weights=replace(options.weights, pose_prior=pose_prior))
        self.options: LMOptions = options
        self.pose_prior = pose_prior
        self.rigid: RigidResult | None = rigid
        self.starts: list[Start] | None = starts
        self.sec: dict[str, float] = {}
        self.clock = StageClock()
        self.centred: PosePrior | None = None  # the declared prior as the rigid stage left it (its pose, its scale)
        self.moved: RigidResult | None = None  # the declared rigid stage's pose relative to the given one
        self.trimmed_fit: Trimmed | None = None  # the pose choice's trimmed fit, made beside the search
        self.screened: list[tuple[float, RigidResult, LibrResult]] = []  # (Ω after screening, candidate, fit)
        self.choice: PoseChoice | None = None
        self.determinacy: Determinacy | None = None
        self.local: dict = {}
        self.result: LibrResult | None = None
        self.quality: FitQuality | None = None
        self.local_modes: LocalModes | None = None
        self.base_model: RegistrationModel | None = None  # today's model, where local modes extended it
        self.folds_support: Support | None = None  # the local-mode step's cross-validation of the answer's basis
        # the error estimate made beside the folds, and what it read (model, rigid, fit, data, weights)
        self.ahead: list[tuple[tuple, OrganError]] = []
        self.early: Support | None = None  # the cross-validation made beside the deformable fit, of ``early_local``
        self.early_local: dict | None = None
        self.beside_s = 0.0  # seconds of that lap beyond the fit's own (counted as the support's)
        self.support: Support | None = None
        self.evidence: PoseEvidence | None = None

    def run(self) -> Registration:
        self.rigid_stage()
        if self.deform:
            self.deformable_stage()
        self.support_stage()
        self.declared_answer()
        if self.choice is not None:
            self.choice = with_turn(self.choice, self._rigid)  # ICP's pose is final here
        self.given_pose_again()
        cancel, result = self.cancel, self.result
        if cancel is not None and cancel.is_set() and result is not None and result.stop_reason != "cancelled":
            # asked to stop after LM had converged, during the cross-validation or the given-pose fit: the
            # checks were cut short, so the answer is unfinished — cancelled, as one stopped mid-fit (the
            # viewer had told the surgeon the previous result is kept, and then showed this one)
            self.result = replace(result, stop_reason="cancelled")
            self.support = None
        reg = Registration(self.model, self._rigid, self.result, self.local, self.sec, self._starts, self.quality,
                           self.choice, self.determinacy, self.support, self.notes, local_modes=self.local_modes,
                           pose_prior=self.options.weights.pose_prior, pose_evidence=self.evidence)
        self.answer_checks(reg)
        self.organ(reg)
        # last, so that it steers nothing above (a note before the pose choice would skip it): too
        # little of the liver covered is said by every caller — the CLI and result.json as the viewer.
        # Not where a declared pose's posterior already says how far the pose may be off (the rigid
        # answer's ``PoseEvidence``, the deformable answer's ``OrganError.pose_mm``, each against the
        # clinical goal): the coverage rule (10 % of the surface) stands for a pose the data must find
        # alone, and said twice it also hid the organ's own line (docs/decisions/registration.md,
        # "issue 46, session 35")
        if not (self.declared and (reg.pose_evidence is not None or reg.organ is not None)):
            note_coverage(reg)
        self.clock.mark("coverage")
        reg.stages = self.clock.times
        return reg

    @property
    def _rigid(self) -> RigidResult:
        assert self.rigid is not None  # set by ``rigid_stage``
        return self.rigid

    @property
    def _starts(self) -> list[Start]:
        assert self.starts is not None  # a list after ``rigid_stage``
        return self.starts

    def _cancelled(self) -> bool:
        return self.cancel is not None and self.cancel.is_set()

    # --- the pose ----------------------------------------------------------------------------

    def rigid_stage(self) -> None:
        """The pose the deformable fit starts from (``rigid``), with its starts, the undeclared
        pose choice (``choice``) and how far the data determine the pose (``determinacy``)."""
        model, data, options, init = self.model, self.data, self.options, self.init
        given, declared = self.given, self.declared
        features = _rigid_features(init)
        t = time.perf_counter()
        rigid, starts = self.rigid, self.starts
        if declared:
            assert self.pose_prior is not None
            if given is None:
                rigid, self.centred, starts = _declared_rigid(model, data, self.pose_prior, options, init, self.cancel)
                self.moved = rigid
            else:  # the same fit on the data moved into the given pose's frame, then composed with it
                self.moved, self.centred, starts = _declared_rigid(
                    model, {n: given.inverse(p) for n, p in data.items()}, self.pose_prior, options, init, self.cancel)
                rigid = after(given, self.moved)
                for s in starts:
                    s.R0, s.t0 = given.R @ s.R0, given.R @ s.t0 + given.t
                    s.result = None if s.result is None else after(given, s.result)
            options = self.options = replace(options, weights=replace(options.weights, pose_prior=self.centred))
        elif rigid is not None or not init.multi_start:
            starts = []
        choosing = not self.warm and not declared and init.keep_given_pose and "fiducials" not in data and \
            not self.notes
        pose_ahead = rigid is None and init.multi_start and choosing and fresh_threads() > 1
        if pose_ahead:
            # the pose choice's trimmed fit from the given pose reads the data alone, not the search's
            # answer: on two cores it is made beside the multi-start search and the screening, each the
            # same computation as in turn (docs/decisions/speed.md, "The fresh registration's
            # independent parts side by side")
            given_starts = starts
            both: list = in_threads(lambda i: self._searched(self._own(given_starts)) if i == 0 else
                                    trimmed_from_given(model, data, _given()), 2)
            starts, rigid = cast(tuple[list[Start], RigidResult], both[0])
            self.trimmed_fit = cast(Trimmed | None, both[1])
            self.clock.mark("rigid_search")
        else:
            if not declared and rigid is None and init.multi_start:
                starts = self._own(starts)
            self.clock.mark("declared_rigid" if declared else "multi_start")
            assert starts is not None
            if rigid is None:
                if init.multi_start:
                    starts, rigid = self._searched(starts)
                else:
                    rigid = rigid_icp(model, data, options.weights, tol_mm=TOL_BEFORE_LIBR if self.deform else 1e-4,
                                      features=features, multi_start=False, robust=init.rigid_robust)
            self.clock.mark("screening")
        assert starts is not None and rigid is not None
        if not declared:  # the declared rigid stage marked its own choice and finished its pose
            for s in starts:
                s.chosen = s.result is rigid
        if starts and not declared:
            # the chosen basin's pose is finished by today's exact point-to-point ICP: on the
            # phantom cases LIBR went on to a lower Ω and TRE from it than from the
            # vertex-matched point-to-plane pose (e.g. 0.48 against 0.95 mm). Starting it from
            # the basin's pose, not the tracker's, keeps the result independent of the offset. A basin
            # that turns the organ further than a tracker errs is finished to convergence, as the
            # rigid-only answer is: whether the pose alone makes such a turn good is asked of it
            # (``PoseChoice.unconfirmed_turn``), and stopped at ``TOL_BEFORE_LIBR`` it can end short
            # along a shallow valley (hard case "90 deg" at 12 mm: 81° with 43 % of the data within
            # 1 mm of the model, 89° and 85 % converged; docs/decisions/registration.md, "The undeclared pose choice …")
            loose = self.deform and turn_deg(rigid) <= POSE_RULE.tracker_turn_deg
            rigid = rigid_icp(model, data, options.weights, tol_mm=TOL_BEFORE_LIBR if loose else 1e-4,
                              start=rigid, features=features, robust=init.rigid_robust)
        self.clock.mark("icp")
        if choosing:
            choice = choose_pose(model, data, _given(), rigid, trimmed=self.trimmed_fit) if pose_ahead else \
                choose_pose(model, data, _given(), rigid)
            if choice.kept:
                trimmed = choice.local
                rigid = trimmed if choice.source is PoseSource.LOCAL and trimmed is not None else \
                    _given(rms_on_model(model, data, _given()))
                for s in starts:
                    s.chosen = False
            self.choice = choice
        if rigid.kept and options.weights.pose_prior is None:
            self.options = replace(options, pose=False)
        # with a declared pose the prior fixes what the data leave free: no sliding direction to report
        self.clock.mark("pose_choice")
        self.determinacy = None if declared else pose_determinacy(model, data, rigid)
        self.clock.mark("determinacy")
        self.sec["rigid"] = time.perf_counter() - t
        self.rigid, self.starts = rigid, starts
        self.local = {name: rigid.inverse(p) for name, p in data.items()}

    def _screen(self, candidates: list[RigidResult], starts: list[Start]) -> RigidResult:
        """The candidate poses' screening (into ``screened``): the pose chosen."""
        init, data = self.init, self.data
        if not (len(candidates) > 1 and init.screen_iterations > 0 and data):
            return candidates[0]
        # which basin: the LIBR objective after a few iterations, not the rigid RMS alone —
        # a pose that leaves the data a few mm off may be the one the deformation explains
        quick = replace(self.options, max_iterations=init.screen_iterations)
        # independent fits: on both cores, each the same as alone, in the candidates' order
        # (docs/decisions/speed.md, "The folds on both cores")
        quick_fits = in_threads(lambda i: register_libr(self.model, {n: candidates[i].inverse(p)
                                                                     for n, p in data.items()},
                                                        None, quick, None, self.cancel), len(candidates))
        self.screened.extend((res.omega, cand, res) for cand, res in zip(candidates, quick_fits, strict=True))
        self.screened.sort(key=lambda x: x[0])
        for s in starts:
            s.omega = next((o for o, c, _ in self.screened if c is s.result), None)
        return self.screened[0][1]

    def _searched(self, starts: list[Start]) -> tuple[list[Start], RigidResult]:
        """The multi-start ICP's starts, and the best of its basins' poses after the screening."""
        return starts, self._screen([s.fitted for s in basin_representatives(starts)[:self.init.max_candidates]],
                                    starts)

    def _own(self, given_starts: list[Start] | None) -> list[Start]:
        """The multi-start ICP, or a copy of the caller's (this registration marks its own omega, chosen)."""
        if given_starts is None:
            return _multi_start(self.model, self.data, self.options, self.init)
        return [replace(s) for s in given_starts]

    # --- the deformation ---------------------------------------------------------------------

    def _fit(self, local: dict, options: LMOptions, callback=None) -> LibrResult:
        b0 = self.beta0
        if self.init.stiff_first and b0 is None:
            # continuation is for leaving a wrong basin from the rigid pose; a warm start
            # (β0 given: the last state, e.g. after adding a plane) continues from there
            stiff = replace(options, weights=replace(options.weights,
                                                     energy=options.weights.energy * self.init.stiff_first))
            b0 = register_libr(self.model, local, b0, stiff, None, self.cancel).beta
        return register_libr(self.model, local, b0, options, callback, self.cancel)

    def _organ_beside(self, made: tuple) -> None:
        reg = Registration(made[0], made[1], made[2], made[3], pose_prior=made[4].pose_prior)
        self.ahead.append((made, organ_error(reg, weights=replace(made[4], pose_prior=None))))

    def deformable_stage(self) -> None:
        """LIBR from the pose (``result``, ``quality``); on two cores the cross-validation's folds
        begin beside it (``early``). A poor fit tries the other basins; local modes extend the
        basis where they earn it."""
        init, cancel, rigid = self.init, self.cancel, self._rigid
        model, local, options = self.model, self.local, self.options
        t = time.perf_counter()
        if self.fresh and init.support is not None and not self.declared and init.local_modes is None and \
                fresh_threads() > 1 and not self._cancelled():
            # the folds read the data and the pose, not the fit of all the data: on two cores they
            # begin on the helper while this thread fits, and the error estimate from ICP's pose
            # follows the fit among them. Where the fit is then replaced (a poor fit refitted from
            # another basin) they are made again below (docs/decisions/speed.md, "The fresh
            # registration's independent parts side by side")
            fitted: list[LibrResult] = []
            after_fit: Callable[[], None] | None = None
            if not rigid.kept:
                at, data_at, weights_at = rigid, local, options.weights

                def estimate() -> None:
                    self._organ_beside((model, at, fitted[0], data_at, weights_at))

                after_fit = estimate
            lead_s: list[float] = []

            def lead() -> None:
                t0 = time.perf_counter()
                fitted.append(self._fit(local, options, self.callback))
                lead_s.append(time.perf_counter() - t0)

            t_batch = time.perf_counter()
            self.early = check_support(model, local, options, init.support, cancel, beside=after_fit, lead=lead)
            self.early_local, result = local, fitted[0]
            # ``seconds``: the fit's own wall time is the deformable stage's, the rest of the lap the support's
            self.beside_s = time.perf_counter() - t_batch - lead_s[0]
            self.clock.mark("deformable+support")
        else:
            result = self._fit(local, options, self.callback)
        if self.declared and result.stop_reason != "cancelled":
            result, options = _settle_scale(model, local, result, options, cancel)
            self.options = options
        quality = assess_fit(result.features)
        stopped = result.stop_reason == "cancelled"
        if not quality.ok and init.retry_poor_fit and len(self.screened) > 1 and not stopped:
            # the fit stayed far off: the other basins get a full fit before anyone is told,
            # and one replaces it only if its fit is plausible (a lower Ω that is still
            # flagged is no reason to prefer it)
            for _, cand, res in self.screened[1:]:
                other_local = {n: cand.inverse(p) for n, p in self.data.items()}
                other = register_libr(model, other_local, res.beta, options, None, cancel)
                other_quality = assess_fit(other.features)
                if other_quality.ok and (quality.ok is False or other.omega < result.omega):
                    for s in self._starts:
                        s.chosen = s.result is cand
                    self.rigid, self.local, result, quality = cand, other_local, other, other_quality
        self.result, self.quality = result, quality
        self.sec["deformable"] = time.perf_counter() - t - self.beside_s
        self.clock.mark("deformable")
        if self.fresh and init.local_modes is not None and result.stop_reason != "cancelled":
            t = time.perf_counter()
            extended, self.local_modes, self.folds_support = choose_local_modes(
                model, self.local, result.beta, options, init.support or SupportOptions(), init.local_modes, cancel)
            if extended is not None:
                self.base_model, self.model = model, extended  # ``_fit`` and every check below use the extended model
                self.result = self._fit(self.local, options)
                self.quality = assess_fit(self.result.features)
            self.sec["local_modes"] = time.perf_counter() - t
            self.clock.mark("local_modes")

    def support_stage(self) -> None:
        """The cross-validation of a fresh deformable answer (``support``)."""
        init, result = self.init, self.result
        if not (self.deform and self.fresh and init.support is not None and result is not None and
                result.stop_reason != "cancelled"):
            return
        t = time.perf_counter()
        model, options, rigid, local, declared = self.model, self.options, self._rigid, self.local, self.declared
        # a declared pose within the clinical goal confines the pose: the held-out gain is judged
        # against its own standard error; declared wider, the rigid stage searches within that
        # width, and the margin that stands for a searched pose holds (docs/decisions/registration.md, "issue 46,
        # session 37"). Measured on the free-floating basis only: on a basis held at declared
        # supports it kept a deformation 1 mm worse than no correction, unwarned (tool1-a), and
        # the margin holds there ("The one-standard-error rule on a held basis", session 37)
        confined = declared and options.weights.pose_prior is not None and model.basis.settings.supports is None \
            and declared_spread(model, options.weights) <= CLINICAL_GOAL_MM
        beside = None
        if not declared and not rigid.kept and not self.ahead:
            # the answer's error estimate, made among the folds' tasks on the second core: from
            # ICP's pose the deformable answer is shown whatever the folds say, and it is used
            # below only if nothing it reads was replaced (docs/decisions/speed.md, "The folds on both cores")
            made = (model, rigid, result, local, options.weights)

            def beside() -> None:
                self._organ_beside(made)

        beside_these = self.early_local is not None and self.early_local is local  # the folds made beside the fit
        if beside_these and self.early is None:
            self.support = None  # too few points to split, or cut short by a cancel: as made here, nothing
        else:
            self.support = _cross_validate(model, local, options, init.support, self.cancel, rigid, result,
                                           self.early if beside_these else self.folds_support,
                                           local_modes=self.base_model is not None, declared=declared,
                                           paired=confined, beside=beside)
        self.sec["support"] = time.perf_counter() - t + self.beside_s
        self.clock.mark("support")

    # --- the answer with a declared pose; the given pose asked again --------------------------

    def declared_answer(self) -> None:
        """With a declared pose and no supported deformation: the rigid answer, the fitted pose or
        the given one by whether the posterior tells them apart (``evidence``)."""
        support, result, options = self.support, self.result, self.options
        if not (self.declared and support is not None and not support.supported and result is not None and
                result.stop_reason != "cancelled" and self.centred is not None and
                options.weights.pose_prior is not None and self.moved is not None):
            return
        model, data = self.model, self.data
        # the rigid answer with a declared pose: the fitted pose or the given one, by whether the
        # posterior tells them apart; within the goal, at the scale of the misfit the rigid fit
        # leaves (``PoseEvidence``; docs/decisions/registration.md, "One criterion for the pose",
        # "A declared rigid move judged at the scale of the misfit it leaves"). Declared wider than
        # the goal, the rigid answer is the one the cross-validation weighed the deformation
        # against: τ, θ refitted with the prior at the deformable answer's settled scale
        # (``_rigid_at_settled_scale``); within it, the given pose is the reference the move is
        # judged against at the misfit's scale, from the rigid stage's pose
        if declared_spread(model, options.weights) > CLINICAL_GOAL_MM:
            refit = _rigid_at_settled_scale(model, data, options, self.cancel, self.moved, self._rigid, result)
            if refit is not None:
                self.moved, self.rigid, self.local, self.centred, result = refit
                options = replace(options, weights=replace(options.weights, pose_prior=self.centred))
        assert self.moved is not None and self.centred is not None
        self.evidence = pose_evidence(model, self.local, self.moved, self.centred, options.weights)
        if self.evidence.kept_given:
            # the deformable fit re-expressed about the given pose, so that its β and the data's
            # frame stay one pair (the error estimate and a warm start read them together)
            result = replace(result, beta=_rebased(model, result.beta, self.moved))
            at = self.given if self.given is not None else _given()
            self.rigid = replace(at, rms_mm=rms_on_model(model, data, at), kept=True)
            self.local = {n: self.rigid.inverse(p) for n, p in data.items()}
            assert options.weights.pose_prior is not None
            options = replace(options, weights=replace(options.weights, pose_prior=replace(
                options.weights.pose_prior, centre=(0.0,) * 6)))
        self.result, self.options = result, options

    def given_pose_again(self) -> None:
        """From ICP's pose, an answer in doubt (a poor fit, an unsupported deformation, a turn no
        tracker makes): does the given pose, held, fit as well? If so it replaces the answer."""
        result, quality, choice, support = self.result, self.quality, self.choice, self.support
        if not (self.fresh and result is not None and quality is not None and choice is not None and
                choice.source is PoseSource.FITTED and result.stop_reason != "cancelled" and
                (not quality.ok or (support is not None and not support.supported) or choice.unconfirmed_turn())):
            return
        t = time.perf_counter()
        model, data, init = self.model, self.data, self.init
        held = replace(self.options, pose=False)
        at_given = self._fit(data, held)
        fits = PoseFits(pooled_rms(result.features), pooled_rms(at_given.features), shift_mm(self._rigid, data))
        preferred = prefer_given(choice, fits)
        if preferred is None and at_given.stop_reason != "cancelled":
            # ICP's pose stays: the fit earned its move, and no line says its pose is in doubt (the
            # doubt that asked — a poor fit, the cross-validation — keeps its own line)
            self.choice = compared(choice, fits)
        elif preferred is not None and at_given.stop_reason != "cancelled":
            self.choice, self.options = preferred, held
            self.rigid = _given(rms_on_model(model, data, _given()))
            self.local, self.result, self.quality = dict(data), at_given, assess_fit(at_given.features)
            self.determinacy = pose_determinacy(model, data, self.rigid)
            for s in self._starts:
                s.chosen = False
            if init.support is not None:
                refolded = None
                if (base := self.base_model) is not None and (modes := init.local_modes) is not None and \
                        self.local_modes is not None:
                    # at the given pose the choice is made again, each fold with its own sources
                    pair = check_support_pair(base, self.local, held, init.support, self.cancel,
                                              extend=lambda train, b: fold_model(base, train, b, modes))
                    if pair is not None:
                        self.local_modes.heldout_base_mm, self.local_modes.heldout_extended_mm = (
                            pair[0].deformable_mm, pair[1].deformable_mm)
                        self.local_modes.adopted = pair[1].deformable_mm < (1 - modes.min_gain) * pair[0].deformable_mm
                        if not self.local_modes.adopted:  # the modes do not earn their place here: today's basis
                            self.model, self.base_model = base, None
                            self.result = self._fit(self.local, held)
                            self.quality = assess_fit(self.result.features)
                        refolded = pair[1] if self.local_modes.adopted else pair[0]
                self.support = _cross_validate(self.model, self.local, held, init.support, self.cancel, self.rigid,
                                               self.result, refolded, local_modes=self.base_model is not None)
        self.sec["given_pose"] = time.perf_counter() - t
        self.clock.mark("given_pose")

    # --- the answer's checks -----------------------------------------------------------------

    def answer_checks(self, reg: Registration) -> None:
        """With declared supports: the surface forces' choice (``reg.forces``), or the held answer
        checked against the free-floating basis on the same held-out blocks (``reg.held``)."""
        model, result, options, init, support = self.model, self.result, self.options, self.init, self.support
        live = result is not None and result.stop_reason != "cancelled"
        if self.surface_forces and self.deform and self.fresh and live and \
                surface_points(self.local).shape[0] >= SupportOptions.min_points:
            assert result is not None
            t = time.perf_counter()
            sf = SurfaceForces(model.basis)
            unheld = self.undeclared if self.undeclared is not None else free_model(model)
            try:
                prior = options.weights.pose_prior
                reg.forces = choose_deformation(sf, model, self.local, result.beta, options, cancel=self.cancel,
                                                free=unheld, pose=PoseTerm.of(prior, model.centroid)
                                                if self.declared and prior else None)
            finally:
                sf.close()
            if init.support is not None and not self._cancelled():
                # the answer held at the supports is judged against the free-floating basis's fits as a
                # held basis's answer is (``HeldCheck``: the undeclared rule, the paired gain, and in
                # ``register`` the change over the organ): without it an answer the supports alone made
                # was worse than the undeclared one with no line (docs/decisions/local-loads.md,
                # "Wrong supports with the surface forces")
                margin, paired = verdict_rule(self.local, self._free_rule(unheld))
                reg.held = reg.forces.held_check(str(model.basis.settings.supports), margin, paired)
            self.sec["forces"] = time.perf_counter() - t
            self.clock.mark("forces")
        elif self.surface_forces and self.deform and not self.fresh:
            reg.warm_without_forces = True
        elif model.basis.settings.supports is not None and self.deform and self.fresh and support is not None and \
                init.support is not None and live:
            # declared supports are a hypothesis the data can contradict: the free-floating basis's
            # fits to the same held-out blocks (docs/decisions/local-loads.md, "Declared supports tested by the data")
            t = time.perf_counter()
            unheld = self.undeclared if self.undeclared is not None else free_model(model)
            free = check_support(unheld, self.local, options, self._free_rule(unheld), self.cancel)
            if free is not None and not self._cancelled():
                # the held answer's gain over the free basis's fits, block by block (the same folds)
                pairs = [Block(h.centre, h.points, f.deformable_mm, h.deformable_mm if reg.deformed else h.rigid_mm)
                         for h, f in zip(support.blocks, free.blocks, strict=False) if np.allclose(h.centre, f.centre)]
                gain, se = paired_gain(pairs) if pairs and len(pairs) == len(support.blocks) == len(free.blocks) \
                    else (math.nan, math.nan)
                reg.held = HeldCheck(str(model.basis.settings.supports),
                                     support.deformable_mm if reg.deformed else support.rigid_mm, free.deformable_mm,
                                     held_deforms=reg.deformed, free_rigid_mm=free.rigid_mm, free_earns=free.predicts,
                                     gain_mm=gain, gain_se_mm=se)
            self.sec["supports_check"] = time.perf_counter() - t
            self.clock.mark("supports_check")

    def _free_rule(self, unheld: RegistrationModel) -> SupportOptions:
        """The cross-validation settings the free-floating basis's fits are judged by, as the
        undeclared registration judges its own deformation: the one-standard-error rule where the
        declared pose confines it within the clinical goal, else the margin (the held-out RMS is the
        same either way)."""
        assert self.init.support is not None
        confined = self.declared and self.options.weights.pose_prior is not None and \
            declared_spread(unheld, self.options.weights) <= CLINICAL_GOAL_MM
        return replace(self.init.support, surface_se=True) if confined else self.init.support

    def organ(self, reg: Registration) -> None:
        """A fresh deformable answer's predicted error over the organ (``reg.organ``)."""
        result = self.result
        if not (self.fresh and reg.deformed and result is not None and result.stop_reason != "cancelled"):
            return
        # every check above compares the answer with simpler ones on the data; this one asks
        # whether it is good enough to navigate by at all (docs/decisions/error-estimate.md, "An answer the data
        # do not determine"). Warm re-registrations skip it, as they skip the cross-validation
        # with the fit's own weights (its robust factors), as the viewer's predicted error is made
        read = (reg.model, reg.rigid, reg.libr, reg.data_model_frame, self.options.weights)
        if self.ahead and all(a is b for a, b in zip(self.ahead[0][0], read, strict=True)):
            reg.organ = self.ahead[0][1]  # made beside the folds from the same answer (its seconds there)
        else:
            reg.organ = organ_error(reg, weights=replace(self.options.weights, pose_prior=None))
        self.sec["organ_error"] = reg.organ.seconds
        self.clock.mark("organ_error")


def write_outputs(case: Case, reg: Registration, out: Path, extra: dict,
                  write_more: Callable[[Path], None] | None = None, targets: Iterable[FitWarning] = ()) -> dict:
    """Registered liver/vessels (PLY), displaced targets (CSV) and result.json, written to
    a temporary folder that replaces ``out`` whole, under ``out``'s lock (``navapp.outputs``).
    ``write_more(folder)`` writes the caller's own files (the registered tumours) into the
    same folder first: a run that stops half way leaves none of its files beside the last
    run's result. ``targets``: the targets' own warnings (``support.TargetSupport.warning``),
    said in result.json's ``warnings`` after the answer's (``Registration.warnings``)."""
    from ..outputs import folder_lock, staged

    with folder_lock(out), staged(out) as tmp:
        if write_more is not None:
            write_more(tmp)
        return _write_outputs(case, reg, tmp, extra, list(targets))


def _write_outputs(case: Case, reg: Registration, out: Path, extra: dict, targets: list[FitWarning]) -> dict:
    from ..outputs import write_registered

    out = Path(out)
    write_registered(out, reg.transform, {name: getattr(case.preop, name) for name in ("liver", *VESSELS)})
    summary = dict(extra)
    if reg.model.mesher is not None:  # the mesh is part of the answer: which mesher made it, and why
        summary["mesher"] = reg.model.mesher.as_dict()
    summary["answer"] = "deformable" if reg.deformed else "rigid"
    if reg.forces is not None and reg.forces.answer is Answer.FORCES:
        summary["answer"] = "surface forces"
    if reg.pose_prior is not None:  # declared: how far the answer moved the organ from the given pose
        moved = reg.libr.features.get("pose_prior", {}) if reg.libr is not None and reg.deformed else {}
        summary["pose_prior"] = {**reg.pose_prior.as_dict(), "rigid_stage_moved_mm": round(shift_mm(reg.rigid, {
            "nodes": reg.model.basis.nodes}), 3), "rigid_stage_turned_deg": round(turn_deg(reg.rigid), 3),
            **({"libr_moved_mm": round(moved["shift_mm"], 3), "libr_turned_deg": round(moved["turn_deg"], 3)}
               if moved else {})}
    for key, part in (("pose", reg.pose_choice), ("pose_determinacy", reg.determinacy), ("support", reg.support),
                      ("predicted_error", reg.organ), ("local_modes", reg.local_modes),
                      ("pose_evidence", reg.pose_evidence), ("surface_forces", reg.forces),
                      ("supports_check", reg.held)):
        if part is not None:
            summary[key] = part.as_dict()
    lines = texts([*reg.warnings, *targets])
    verdict = Verdict(tuple(lines))  # one rule: ok only with no warning (fit_quality.ok says the same)
    summary["ok"] = verdict.ok
    if reg.quality is not None:
        summary["fit_quality"] = reg.quality.as_dict(verdict)
    summary["warnings"] = lines
    summary["warning"] = "; ".join(lines) if lines else None
    if case.truth is not None:  # reported, never fitted: the TRE at the truth's points (``anatomy.truth``)
        x0, x1 = case.truth.tre_points(reg.model.basis.nodes)
        pred = reg.transform(x0)
        write_csv(out / "targets.csv", np.column_stack([x0, pred]), ("x0", "y0", "z0", "x1", "y1", "z1"))
        summary["tre_rigid"] = tre_stats(reg.rigid.apply(x0), x1).as_dict()
        if reg.libr is not None:
            summary["tre_deformable"] = tre_stats(pred, x1).as_dict()  # the answer: rigid when not ``reg.deformed``
    (out / "result.json").write_text(json.dumps(summary, indent=2))
    return summary
