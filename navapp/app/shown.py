"""The registered model on show, and what is read off it: its geometry (surfaces and
targets, once per state), its error against the truth at the mesh nodes (simulated scenes),
the error predicted without the truth at the surface and at each target (tumour), the
target lines of the ultrasound and stylus readouts, and the result a restarted session
restores. No viser here.

The "state on show" is the streaming state while a registration runs, else the result,
else the preoperative model as-is.
"""

from __future__ import annotations

import numpy as np

from ..fitwarning import FitWarning, WarningKind
from ..geometry.targets_distance import ImagePlane, plane_distances, tip_distances
from ..geometry.tre import point_errors
from ..registration.libr import LibrResult
from ..registration.model import RegistrationModel, deform
from ..registration.pipeline import Registration
from ..registration.rigid import RigidResult
from ..registration.support import target_support
from ..registration.targets import registered_targets, target_interpolation
from .core import Core
from .slicer import Slicer
from .state import CARRIED, ClientState, RegisteredState, StatedSupports, StateGeometry, TargetBand
from .worker import viewer_options

# beside each tumour when the pose is not to be believed: no figure, what to do instead
NO_TARGET_FIGURE = ("no predicted error here: the pose is not to be believed — digitise more of the liver "
                    "surface (or add planes) and register again")
IN_IMAGE_MM = 0.05  # a target this close to the image plane is cut by it


class Shown:
    def __init__(self, core: Core, slicer: Slicer):
        self.core, self.slicer = core, slicer
        self._target_B = None  # interpolation matrix of the target points in the registration mesh
        self._centre_B = None  # the same for the targets' centres (their true error)
        self._geometry: StateGeometry | None = None  # the last state's geometry (see geometry())

    # ------------------------------------------------------------------ positions and errors
    def node_positions(self, rigid: RigidResult, beta: np.ndarray | None,
                       model: RegistrationModel | None = None) -> np.ndarray:
        """All mesh nodes at state β in tracker space, (M, 3) mm (eq. 8, ``registration.model.deform``).
        ``model``: the one β is in (default the free-floating one)."""
        model = model or self.core.need_model()[0]
        nodes = model.basis.nodes
        if beta is None:
            return rigid.apply(nodes)
        n = len(beta) - 6
        u = (model.basis.Ju @ beta[:n]).reshape(-1, 3)
        return rigid.apply(deform(nodes, u, beta, model.centroid)[1])

    def node_error(self, rigid: RigidResult, beta: np.ndarray | None,
                   model: RegistrationModel | None = None) -> np.ndarray | None:
        """(M,) true error at the mesh nodes, mm; None without the truth."""
        truth = self.core.truth_nodes
        if truth is None:
            return None
        return point_errors(self.node_positions(rigid, beta, model), truth)

    def target_errors(self, rigid: RigidResult, beta: np.ndarray | None,
                      model: RegistrationModel | None = None) -> dict[str, float] | None:
        """Each target's (tumour's) true error at its centre, mm: the mesh nodes' error vector
        interpolated there (the truth is known at the nodes); None without the truth."""
        core = self.core
        truth, targets = core.truth_nodes, core.preop.targets
        if truth is None or not targets:
            return None
        if self._centre_B is None:
            from ..geometry.interpolation import interpolation_matrix

            model, _ = core.need_model()
            self._centre_B = interpolation_matrix(model.basis.nodes, model.basis.tets,
                                                  np.array([t.centre for t in targets]))
        # the error vectors interpolated to the centres, then their lengths
        d = point_errors(self._centre_B @ (self.node_positions(rigid, beta, model) - truth), 0.0)
        return {t.name: round(float(e), 3) for t, e in zip(targets, d, strict=True)}

    def predict(self, reg: Registration, checked: Registration | None = None) -> tuple[np.ndarray | None,
                                                                                        list[TargetBand]]:
        """The predicted error without the truth (``registration.uncertainty``): (S,) at the
        surface nodes, and a ``TargetBand`` per target; (None, []) for a rigid result or
        when it cannot be had (too few data). ``checked``: the fresh registration a warm one
        continues from (``RegisteredState.checked``): its held-out blocks' verdicts stand for
        the warm result's, said to be from then, as a warm start does not cross-validate."""
        from ..registration.uncertainty import estimate_error

        model = reg.model
        if reg.libr is None or not reg.data_model_frame:
            return None, []
        preop = self.core.preop
        centres = {t.name: t.centre for t in preop.targets}
        # the data and the targets' preoperative centres are both in the model frame
        verdicts, said = reg.support, None
        if verdicts is None and checked is not None and checked is not reg and checked.support is not None:
            verdicts, said = checked.support, CARRIED
        support = {s.name: s for s in target_support(verdicts, centres, reg.data_model_frame, said)}
        if not reg.deformed:  # the rigid answer: no prediction, the reason beside each target
            # the line ``Registration.warnings`` gives for it, its head: no other verdict beside the
            # targets than the row, result.json and Slicer say (none for a declared pose the data confirm)
            why = reg.why_pose_alone
            short = FitWarning(why.kind, why.head, why.carried) if why is not None else None
            return None, [TargetBand(t.name, float("nan"), float("nan"), float("nan"), short) for t in preop.targets]
        if reg.pose_doubts:
            # a pose nobody should believe (``Registration.pose_doubts``): the calibration was fitted on
            # answers whose pose was right and says nothing at a point 100 mm off (a 40-point patch:
            # tumours 39 and 133 mm off, predicted 202 and 31 mm; the demo's surface 15 × the true
            # error); no figure at the tumours or on the surface, but what to do
            doubt = FitWarning(reg.pose_doubts[0].kind, NO_TARGET_FIGURE)  # it stands for the first doubt
            return None, [TargetBand(t.name, float("nan"), float("nan"), float("nan"), doubt) for t in preop.targets]
        try:
            # with the weights of the fit: points it rejected (a wrong click) do not inflate the
            # residual scale of the prediction (with least squares weights a stray vertex the fit
            # had rightly ignored predicted 31.9 mm at a tumour whose error was 4 mm)
            weights = viewer_options().weights
            surface = estimate_error(reg, nodes=model.basis.surface, weights=weights).predicted_mm
            bands = []
            if preop.targets:
                est = estimate_error(reg, points=np.array([t.centre for t in preop.targets]), weights=weights)
                bands = [TargetBand(t.name, float(e), float(lo), float(hi), support[t.name].warning)
                         for t, e, lo, hi in zip(preop.targets, est.predicted_mm, est.lower_mm, est.upper_mm,
                                                 strict=True)]
            return surface, bands
        except (np.linalg.LinAlgError, ValueError):
            return None, []

    def surface_error(self, cs: ClientState, node_error: np.ndarray | None = None) -> np.ndarray | None:
        """(S,) the error this tab colours the registered surface by: the predicted error
        of the result on show, or the true error (``node_error`` (M,) of a streaming state,
        else the result's) when the truth is known and the tab chose it."""
        core = self.core
        res = core.result
        if cs.error_source == "predicted" or core.truth_nodes is None or core.model is None:
            return None if res is None or node_error is not None else res.predicted_mm
        e = node_error if node_error is not None else (res.node_error_mm if res is not None else None)
        return None if e is None else e[core.model.basis.surface]

    # ------------------------------------------------------------------ geometry
    def geometry(self, rigid: RigidResult | None = None, beta: np.ndarray | None = None,
                 surfaces: dict | None = None, model: RegistrationModel | None = None) -> StateGeometry:
        """The model at a registered state, computed once per state (the last one is kept):
        by default the state on show. ``surfaces``: the worker's vertices for this state
        when it already has them (name → (V, 3)); ``model``: the one β is in (default the
        free-floating one)."""
        core = self.core
        if rigid is None:
            run = core.run
            if run is not None and run.state is not None:
                (rigid, beta), model = run.state, run.model
            elif core.result is not None:
                rigid, beta, model = core.result.rigid, core.result.beta, core.result.model
        g = self._geometry
        if g is not None and g.rigid is rigid and g.beta is beta:
            return g
        pre = core.preop.targets
        if rigid is None or core.model is None or core.worker is None:
            g = StateGeometry(None, None, {}, pre)
        else:
            model = model or core.model
            if surfaces is None:
                surfaces = core.worker.surfaces(rigid, beta, model)
            cells = {name: model.features[name].cells for name in surfaces}
            reg = Registration(model, rigid, None, {})  # transform: rigid ∘ eq. 8 at β
            if pre and self._target_B is None:  # locating the target points in the mesh once
                self._target_B = target_interpolation(reg, pre)
            moved = registered_targets(reg, pre, beta, self._target_B) if pre else []
            g = StateGeometry(rigid, beta, {n: (v, cells[n]) for n, v in surfaces.items()}, moved)
        self._geometry = g
        return g

    # ------------------------------------------------------------------ target readouts
    def target_plane_lines(self, index: int, short: bool = False) -> list[str]:
        """One line per target: its distance from this plane's image (0: the image cuts it)
        and, for a result on show, its predicted error (and the result's warning for it;
        ``short``: its first clause, ``TargetBand.text``)."""
        core = self.core
        g = self.geometry()
        targets = g.targets
        if not targets or index not in core.planes or core.sd is None:
            return []
        # named by the state the distances are of: a first run had them "registered" while they were
        # still the preoperative ones (until its first state came; a rigid run's whole length)
        which = "registered" if g.rigid is not None else "preoperative"
        p = core.sd.probe
        plane = ImagePlane.from_pose(core.planes[index].probe_to_tracker, p.width_px * p.spacing_mm,
                                     p.height_px * p.spacing_mm)
        bands = {b.name: b for b in core.result.target_bands} if core.result is not None else {}
        # the result on show is the state drawn (no run streaming one of its own) and nobody should believe its pose
        doubted = (core.result is not None and bool(core.result.pose_warning)
                   and g.rigid is core.result.rigid and g.beta is core.result.beta)
        out = []
        for t, d in zip(targets, plane_distances(plane, targets), strict=True):
            # kept while a run streams: it is the band of the result still on show (Cancel keeps
            # it), and lines that lost it moved the Registration panel's Cancel from under the mouse
            band = bands.get(t.name)
            said = band.text(short) if band is not None else ""
            if not said and doubted:
                # a rigid answer has no band: one plane's wall 33.5 mm off read "tumour1 (registered):
                # in this image", nothing beside it, under the red banner
                said = "⚠ pose not to be believed"
            out.append(f"**{t.name}** ({which}): " +
                       ("in this image" if d <= IN_IMAGE_MM else f"{d:.1f} mm from this image") +
                       (f"; {said}" if said else ""))
        return out

    def target_distance_lines(self, tip) -> list[str]:
        """One line per target: the stylus tip's distance to its surface."""
        targets = self.geometry().targets
        if not targets or tip is None:
            return []
        return [f"**{t.name}**: " + (f"tip inside, {-d:.1f} mm deep" if d < 0 else f"{d:.1f} mm from the stylus tip")
                for t, d in zip(targets, tip_distances(tip, targets), strict=True)]

    # ------------------------------------------------------------------ restart
    def restore(self):
        """The registered model stored in the session (rigid pose and β) after a restart."""
        core = self.core
        free, worker = core.need_model()
        d = core.need_session().result
        if not d:
            return
        try:  # the model β is in: held at the supports stated when it was fitted, or free-floating
            held = StatedSupports.from_json(d["supports"]).held if d.get("supports") is not None else None
        except ValueError:
            return  # a record this version cannot read: nothing to restore
        model = free if held is None else core.build_held(held)
        rigid = RigidResult(np.array(d["R"]), np.array(d["t"]), 0, float(d.get("rms_mm", np.nan)),
                            kept=bool(d.get("kept", False)))
        beta = None if d.get("beta") is None else np.array(d["beta"], float)
        if beta is not None and len(beta) != model.basis.Ju.shape[1] + 6:
            return  # another basis size (different --k): nothing to restore
        libr = None if beta is None else LibrResult(beta, float("nan"), 0, "restored", [], [], {}, 0.0, {})
        # the data the fit was made from (model frame): the predicted error and the next-plane
        # suggestion are only meaningful on them (the LM covariance is scaled by the fit's own
        # residuals; data added since inflated a restored demo's organ mean to 113.63 mm beside
        # targets at 2.8 and 5.2 mm). A session saved before they were kept has none: its saved
        # prediction is shown, and a suggestion asks for a new registration
        inv = {k: np.asarray(v, float).reshape(-1, 3) for k, v in (d.get("data_model_frame") or {}).items()}
        doubt = d.get("pose_warning")
        reg = Registration(model, rigid, libr, inv, notes=[FitWarning(WarningKind.SAVED, doubt)] if doubt else [])
        core.last_reg = worker.last = reg
        predicted = self.predict(reg)
        saved = d.get("predicted_mm")
        if saved is not None and len(saved) == len(model.basis.surface):
            predicted = (np.array(saved, float), [TargetBand.from_json(b) for b in d.get("target_bands", [])])
        core.result = RegisteredState(d.get("run", "restored"), rigid, beta, self.node_error(rigid, beta, model),
                                      *predicted, data_model_frame=inv, pose_warning=doubt, restored=True,
                                      model=core.kept_model(model))
        self.slicer.send(reg)  # queued: a Slicer connecting later receives the result on show

