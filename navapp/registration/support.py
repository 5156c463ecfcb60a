"""Do the data support the deformable answer? Spatial cross-validation against rigid.

The surface fit can be good while the organ's interior is wrong: a few modes far from the
data bend the organ to share out a local misfit, and no residual shows it. What the data
*can* tell is whether the deformation they imply carries over to where there are no data.
The data points are cut into ``blocks`` spatial blocks (k-means of their positions in
the model frame); for each block the deformable model is fitted to the other blocks and
predicts the held-out one. The rigid answer is fitted to the same blocks (τ, θ alone, or the
kept given pose) and predicts it too. A deformation is *supported* where it predicts
held-out data better than the rigid answer by ``margin`` (relative; ``margin_interior`` when
vessel data inside the organ take part); with a pose declared within the clinical goal and surface
data alone, by more than one standard error of the gain, paired block by block (``paired_gain``).
Where it does not, or where a target is farther than ``far_mm`` from every data point, the
target's correction is not determined by the data.

``register`` (pipeline) returns the given pose without deformation when the deformation is
not supported and the given pose was kept (the data lay on the undeformed model: never
worse than no correction on what the data can show), and says so in one line either way;
per target, ``target_support`` names the targets whose neighbourhood is unsupported.

From a kept pose there is a second question the cross-validation cannot ask: is the
correction itself larger than its own uncertainty? A dent the basis cannot make is fitted
at its rim, and the held-out blocks over the dent are then predicted better than without
deformation, while the organ around it moves by about a millimetre — a small error spread
wide. ``weigh_correction`` compares the mean displacement the deformation adds at the mesh
nodes with the mean σ there (the LM covariance propagated to the nodes, as the error
estimate computes it, ``uncertainty``); a correction under ``z`` σ is not told apart from
none, and the kept pose, which the data lie on, is the answer.

From ICP's pose the deformable answer is shown whatever the verdict (no pose there is a
known-good answer without deformation), and the verdict only decides whether to warn. There
the held-out surface is a poor judge: on surface data alone a deformation that lowered the
rigid TRE by a third predicted the held-out blocks no better than the tool loads it harmed.
So where the cross-validation fails from ICP's pose the correction is weighed too, and one
of at least ``z_strong`` σ — a correction the data demand far beyond their noise — is not
warned about (``outweighs``). The answer is the same either way; only the line changes.
"""

import math
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree
from sklearn.cluster import KMeans

from ..features import SALIENT
from ..fitwarning import FitWarning, WarningKind
from ..switches import Before
from ..threads import in_threads, limit_threads, task_threads
from .libr import LMOptions, register_libr
from .model import DATA_TO_MODEL, RegistrationModel
from .objective import Evaluation, evaluate, points_of
from .quality import EXPECTED_NOISE_MM
from .uncertainty import covariance_factor, information, point_jacobian, point_sigma


@dataclass(frozen=True)
class SupportOptions:
    """The spatial cross-validation of ``check_support`` (module doc)."""

    blocks: int = 5
    # the deformable prediction must be this much (relative) better than rigid from surface data
    # alone: on the tool cases whose surface-only deformable answer was worse than none it
    # predicted the held-out data 14–15 % better, where it helped 46–75 % (docs/decisions/local-loads.md,
    # "Local loads"); with vessel data inside the organ, which rule out a wrong interior
    # behind a good surface fit, ``margin_interior``
    margin: float = 0.3
    margin_interior: float = 0.1
    # with a declared pose within the clinical goal and surface data alone: the deformation is
    # supported where it predicts the held-out blocks better than the rigid answer by more than
    # one standard error of that gain, paired block by block (``paired_gain``), in place of
    # ``margin``. The 30 % margin stands for a pose the data find alone, where a slid pose's
    # deformation predicts held-out surface as well as a right one's; such a prior confines the
    # pose (docs/decisions/registration.md, "issue 46, session 37")
    surface_se: bool = False
    far_mm: float = 40.0  # a target farther than this from every data point is extrapolated
    min_points: int = 30  # fewer data points: no cross-validation (too few to split)
    iterations: int = 30  # LM cap per fold (the fold fits start from β = 0)
    # a kept pose's correction must be at least this many σ (means over the mesh nodes):
    # the conventional three; docs/decisions/local-loads.md ("A correction within its own uncertainty")
    # has where the measured cases lie against it
    z: float = 3.0
    # from ICP's pose, a correction of at least this many σ is not warned about where the
    # cross-validation fails (module doc); docs/decisions/error-estimate.md ("The warnings on good answers")
    # has the measured cases on either side of it
    z_strong: float = 4.0
    sample_nodes: int = 2000  # mesh nodes the comparison is made at (every n-th: σ costs time per node)


@dataclass
class Block:
    """One held-out block: where it is and how each answer predicted it (RMS mm)."""
    centre: np.ndarray  # (3,) mm, model frame
    points: int
    rigid_mm: float
    deformable_mm: float

    @property
    def supported(self) -> bool:
        return self.deformable_mm < self.rigid_mm  # the block's own verdict; the global one has a margin


@dataclass
class Support:
    """Held-out prediction error of the rigid and the deformable answers (mean RMS over blocks, mm)."""
    rigid_mm: float
    deformable_mm: float
    blocks: list[Block] = field(default_factory=list)
    margin: float = SupportOptions.margin
    seconds: float = 0.0
    # the held-out gain's standard error (mm, ``paired_gain``); ``paired``: the verdict is the gain
    # against it, not against ``margin`` (``SupportOptions.surface_se``)
    se_mm: float = 0.0
    paired: bool = False
    # from a kept pose (``weigh_correction``): the mean displacement the deformation adds and
    # the mean σ, over the sampled mesh nodes (mm); None where it was not weighed
    correction_mm: float | None = None
    sigma_mm: float | None = None
    z: float = SupportOptions.z
    z_strong: float = SupportOptions.z_strong

    @property
    def predicts(self) -> bool:
        """The cross-validation's verdict: held-out data predicted better than without deformation."""
        if self.paired:
            return self.rigid_mm - self.deformable_mm > self.se_mm
        return self.deformable_mm < (1 - self.margin) * self.rigid_mm

    @property
    def significant(self) -> bool:
        """The correction stands out from its own uncertainty (True where it was not weighed)."""
        if self.correction_mm is None or self.sigma_mm is None:
            return True
        return self.correction_mm >= self.z * self.sigma_mm

    @property
    def supported(self) -> bool:
        return self.predicts and self.significant

    @property
    def outweighs(self) -> bool:
        """The correction is at least ``z_strong`` × its own σ (False where it was not weighed):
        from ICP's pose such an answer is not warned about, whatever the cross-validation said."""
        if self.correction_mm is None or self.sigma_mm is None:
            return False
        return self.correction_mm >= self.z_strong * self.sigma_mm

    @property
    def warning(self) -> str | None:
        return self.warning_for(shown_rigid=True)

    def warning_for(self, shown_rigid: bool, given: bool = True, declared: bool = False) -> str | None:
        """One line when the deformation is not supported, saying which answer is shown
        (``given``: the rigid answer is the given pose, not the trimmed fit's; ``declared``: it
        is the rigid fit with a declared pose prior)."""
        if self.supported or (not shown_rigid and self.outweighs):
            return None
        pose = "the rigid pose fitted within the declared prior" if declared else \
            "the given pose" if given else "the pose most of the data lie on"
        shown = (f"{pose} without deformation is shown" if shown_rigid else
                 "the deformable answer is shown: do not rely on it")
        if self.predicts:
            return (f"deformation not determined by the data: the correction it makes (mean "
                    f"{self.correction_mm:.2f} mm over the organ) is under {self.z:g} × its own uncertainty "
                    f"(σ {self.sigma_mm:.2f} mm) — {shown}; add data where the organ moved")
        # the criterion it failed, said: "1.11 against 1.44 mm" alone reads as support
        by = (f", not better by one standard error ({self.se_mm:.2f} mm)" if self.paired else
              f", {100 * (1 - self.deformable_mm / self.rigid_mm):.0f} % better, under the {100 * self.margin:.0f} % "
              "asked of a deformation" if self.deformable_mm < self.rigid_mm else "")
        return (f"deformation not supported by the data: fitted to part of the data it predicts the rest "
                f"{self.deformable_mm:.2f} mm RMS against {self.rigid_mm:.2f} mm without deformation{by} — "
                f"{shown}; add data where the organ moved")

    def as_dict(self) -> dict:
        return {"supported": self.supported, "heldout_rigid_mm": round(self.rigid_mm, 3),
                "heldout_deformable_mm": round(self.deformable_mm, 3), "margin": self.margin,
                **({"standard_error_mm": round(self.se_mm, 3), "rule": "one standard error"} if self.paired else {}),
                "blocks": [{"centre_mm": np.round(b.centre, 1).tolist(), "points": b.points,
                            "rigid_mm": round(b.rigid_mm, 3), "deformable_mm": round(b.deformable_mm, 3)}
                           for b in self.blocks], "seconds": round(self.seconds, 3),
                **({} if self.correction_mm is None or self.sigma_mm is None else
                   {"correction_mm": round(self.correction_mm, 3), "sigma_mm": round(self.sigma_mm, 3),
                    "z": self.z, "significant": self.significant, "z_strong": self.z_strong,
                    "outweighs": self.outweighs})}


def supports_not_borne_out(free_mm: float, held_mm: float, shown: str) -> str:
    """The one line for declared supports the data contradict (``HeldCheck``,
    ``forces.ForceChoice``): ``shown`` says which answer is shown."""
    return (f"the declared supports are not borne out by the data: the free-floating model predicts held-out "
            f"surface data better ({free_mm:.2f} mm) than the answer held at them ({held_mm:.2f} mm) — {shown}; "
            "check where the organ is held")


@dataclass(frozen=True)
class HeldCheck:
    """Declared supports tested by the data (a model held at them, ``prepare(supports=)``): the
    held-out RMS (mm) of the answer the held model gives, and of the free-floating basis's fits
    to the same folds. Where the free basis predicts the held-out data better (no margin: the
    same criterion as the surface forces' test of the supports), the supports are contradicted,
    and the free-floating model's registration is the answer (``replaced``) unless neither
    answer deforms: two rigid answers the supports do not shape (``pipeline.register``)."""

    held: str  # the declared supports' name
    held_mm: float
    free_mm: float
    replaced: bool = False  # the answer is the free-floating model's registration
    held_deforms: bool = False  # the held answer is deformed
    free_rigid_mm: float = math.nan  # the rigid answer's held-out RMS in the free basis's folds
    # the free basis's folds earn a deformation by the undeclared registration's own rule
    free_earns: bool = True
    # the held answer's held-out gain over the free basis's fits and its paired standard error (mm)
    gain_mm: float = math.nan
    gain_se_mm: float = math.nan
    # RMS over the organ (``uncertainty.organ_nodes``) of the held answer's difference from the
    # free-floating model's registration on the same data, mm; NaN where not measured
    organ_change_mm: float = math.nan

    @property
    def contradicted(self) -> bool:
        return self.free_mm < self.held_mm

    @property
    def undecided(self) -> bool:
        """The held answer predicts the held-out blocks better than the free basis's fits by no more
        than one paired standard error (``paired_gain``): the data do not tell the two apart."""
        return not math.isnan(self.gain_mm) and not self.gain_mm > self.gain_se_mm

    @property
    def borne_out_mm(self) -> float:
        """How much of a change the held-out data bear out, mm: √(free² − held²) of the held-out
        RMS — what the held answer removes from the free basis's held-out misfit, as an RMS of
        the difference between the two (zero where it removes none)."""
        return math.sqrt(max(self.free_mm ** 2 - self.held_mm ** 2, 0.0))

    @property
    def beyond_data(self) -> bool:
        """The declared supports change the answer over the organ (``organ_change_mm``, an RMS)
        by more than the held-out data bear out (``borne_out_mm``): the rest of the change lies
        where no data test it (docs/decisions: "Wrong supports, session 39")."""
        return not math.isnan(self.organ_change_mm) and self.organ_change_mm > self.borne_out_mm

    @property
    def rests_on_supports(self) -> bool:
        """The held answer deforms, and either the free-floating basis's fits earn no deformation
        by the undeclared rule, or the held answer's held-out gain over them is within one paired
        standard error, or it differs from the free-floating answer over the organ by more than the
        held-out data bear out: the declaration, not the data, makes this deformation
        (docs/decisions/local-loads.md, "Wrong supports, session 38", and
        "Wrong supports: the change the supports make, weighed against what the data bear out")."""
        return self.held_deforms and not self.replaced and not self.contradicted and \
            (not self.free_earns or self.undecided or self.beyond_data)

    @property
    def warning(self) -> str | None:
        if self.rests_on_supports:
            why = (f"without them the data earn none (held out {self.free_mm:.2f} mm free-floating against "
                   f"{self.free_rigid_mm:.2f} mm without deformation)" if not self.free_earns else
                   f"the data do not tell them from a free-floating organ (held out {self.held_mm:.2f} mm held "
                   f"against {self.free_mm:.2f} mm free, within one standard error, {self.gain_se_mm:.2f} mm)"
                   if self.undecided else
                   f"they move the organ {self.organ_change_mm:.2f} mm (RMS) from the free-floating answer, more "
                   f"than the {self.borne_out_mm:.2f} mm the held-out data bear out (held out {self.held_mm:.2f} mm "
                   f"held against {self.free_mm:.2f} mm free)")
            return f"the deformation shown rests on the declared supports ({self.held}): {why} — check where the " \
                   "organ is held"
        if not self.replaced:
            return None
        return supports_not_borne_out(self.free_mm, self.held_mm, "the free-floating model's answer is shown")

    def as_dict(self) -> dict:
        return {"held": self.held, "heldout_held_mm": round(self.held_mm, 3), "heldout_free_mm": round(self.free_mm, 3),
                "contradicted": self.contradicted, "replaced": self.replaced,
                "heldout_free_rigid_mm": round(self.free_rigid_mm, 3), "free_earns_deformation": self.free_earns,
                "rests_on_supports": self.rests_on_supports, "gain_mm": round(self.gain_mm, 4),
                "gain_se_mm": round(self.gain_se_mm, 4), "organ_change_mm": round(self.organ_change_mm, 4),
                "borne_out_mm": round(self.borne_out_mm, 4), "beyond_data": self.beyond_data}


def pooled_rms(features: dict, names=None) -> float:
    """RMS residual (mm) over the points of the features ``names`` (default: every data
    feature) of an ``objective.evaluate`` / ``LibrResult`` feature table."""
    names = [k for k in features if "rms_mm" in features[k]] if names is None else names
    n = sum(features[k]["n"] for k in names)
    return math.sqrt(sum(features[k]["n"] * features[k]["rms_mm"] ** 2 for k in names) / n) if n else 0.0


def blocks_of(data: dict, count: int, seed: int = 0) -> dict:
    """feature → (N,) block index of every point: k-means of all points' positions.
    Fiducials (known correspondence, few) stay in every training set (block −1)."""
    pts = np.vstack([p for k, p in data.items() if k != "fiducials"])
    sample = pts[:: max(1, len(pts) // 3000)]
    with limit_threads(1):
        km = KMeans(n_clusters=count, n_init=2, random_state=seed).fit(sample)
    tree = cKDTree(km.cluster_centers_)
    return {k: (np.full(len(p), -1) if k == "fiducials" else tree.query(p)[1]) for k, p in data.items()}


def check_support(model: RegistrationModel, data: dict, options: LMOptions,
                  support: SupportOptions = SupportOptions(), cancel=None,
                  beside: Callable[[], None] | None = None,
                  lead: Callable[[], None] | None = None) -> Support | None:
    """Cross-validate the deformable answer against the rigid one (module doc). ``data``:
    feature → (N, 3) mm in the model frame (after the rigid pose); ``options`` the LM
    settings of the real fit. None when there are too few data points to split. ``beside``,
    ``lead``: the caller's own tasks, run among the folds' when they share the cores
    (``check_support_pair``)."""
    pair = check_support_pair(model, data, options, support, cancel, beside=beside, lead=lead)
    return None if pair is None else pair[0]


def check_support_pair(model: RegistrationModel, data: dict, options: LMOptions,
                       support: SupportOptions = SupportOptions(), cancel=None,
                       extend: Callable[[dict, np.ndarray], RegistrationModel | None] | None = None,
                       beside: Callable[[], None] | None = None,
                       lead: Callable[[], None] | None = None) -> tuple[Support, Support] | None:
    """``check_support`` for ``model`` and, in the same folds, for a model each fold extends
    from its own training data: ``extend(train, beta)`` (the training data, feature →
    (N, 3) mm, and the fit of ``model`` to them, (3k + 6,)) returns the extended model or None
    (the fold keeps ``model``'s prediction). So no held-out point has a say in what its fold's
    model can do (``local_modes``). Without ``extend`` both Supports are the same.

    The folds' fits leave the model's kept fit ends (``objective.keep_end``) as they found them
    (they fit a copy of ``model`` with a copy of its cache): no later fit starts where a fold
    ended, and ten of them would push out the answer's own, which the error estimate and the
    first warm start after a fresh registration evaluate at.

    ``beside``: a task of the caller's that does not depend on the folds (``pipeline``'s error
    estimate of the answer, made ahead), run as one more of their tasks where they run on two
    threads, so that it fills the cores with them; not run where they run on one (nor where there
    are too few points to split), and then the caller makes what it would have made.

    ``lead``: the caller's work that the folds do not read, run first on the calling thread while
    the helper begins with the folds (``threads.in_threads``; ``pipeline``'s deformable fit of all
    the data, whose answer the folds never see): ``beside`` then waits for it, and is not run if
    it failed. Run first on one thread, and run alone where there are too few points to split."""
    total = sum(len(p) for k, p in data.items() if k != "fiducials")
    if total < support.min_points:
        if lead is not None:
            lead()
        return None
    # the folds' fits keep their ends and last evaluations in a cache of their own, begun as a copy
    # of the model's: no fold starts where another fit ended, and the caller's fits (``lead``,
    # ``beside``) keep theirs in the model's own
    return _folds(replace(model, cache=model.cache.copy()), data, options, support, cancel, extend, beside, lead)


def _after(lead: Callable[[], None], beside: Callable[[], None]) -> tuple[Callable[[], None], Callable[[], None]]:
    """``lead`` and ``beside`` such that ``beside`` runs after ``lead`` has ended, and not at all
    when it failed: in ``in_threads`` the lead is this thread's first work, so a task that waits
    for it waits for work under way (never for a task not yet taken)."""
    done, ok = threading.Event(), []

    def first() -> None:
        try:
            lead()
            ok.append(True)
        finally:
            done.set()

    def then() -> None:
        done.wait()
        if ok:
            beside()

    return first, then


def _folds(model, data, options, support, cancel, extend, beside=None, lead=None) -> tuple[Support, Support] | None:
    t0 = time.perf_counter()
    fold = replace(options, max_iterations=min(options.max_iterations, support.iterations))
    n = model.basis.Ju.shape[1]
    zero = np.zeros(n + 6)
    made: list[tuple[dict, Evaluation, dict[int, _Fold]]] = []  # (labels, the shared start, block → fold)
    making = threading.Lock()

    def prepared() -> tuple[dict, Evaluation, dict[int, "_Fold"]]:
        """The blocks, the shared start and the folds, made by the first task (on the helper while
        this thread runs a ``lead``); a task of the other thread waits for them."""
        with making:
            if not made:
                labels = blocks_of(data, support.blocks)
                # every fold's fits start at β = 0, on some of these points: one evaluation of all of
                # them there, and each fit starts from its training points' rows (``objective.points_of``:
                # the same bits as evaluating them apart, ten searches and Jacobians fewer)
                with limit_threads(1):
                    start = evaluate(model, data, zero, options.weights, jacobian=True)
                folds = [_Fold(b, {k: p[labels[k] != b] for k, p in data.items() if (labels[k] != b).any()},
                               {k: p[labels[k] == b] for k, p in data.items() if (labels[k] == b).any()})
                         for b in range(support.blocks)]
                made.append((labels, start, {f.block: f for f in folds if f.train and f.held}))
            return made[0]

    def first(f: "_Fold"):
        # the fold's rows of the shared start, made once for its two fits (whichever runs first)
        labels, start, _ = prepared()
        with f.lock:
            if f.first is None:
                f.first = points_of(start, {k: labels[k] != f.block for k in f.train}, options.weights)
            return f.first

    def deformable(f: "_Fold") -> tuple[float, float] | None:
        if cancel is not None and cancel.is_set():
            return None  # cut short: folds stopped before they were fitted say nothing about the data
        fit = register_libr(model, f.train, None, fold, None, cancel, first=first(f))
        deformed = pooled_rms(evaluate(model, f.held, fit.beta, options.weights, jacobian=False).features, f.held)
        if cancel is not None and cancel.is_set():
            return None
        other = None if extend is None else extend(f.train, fit.beta)
        extended = deformed
        if other is not None:
            fit2 = register_libr(other, f.train, None, fold, None, cancel)
            extended = pooled_rms(evaluate(other, f.held, fit2.beta, options.weights, jacobian=False).features,
                                  f.held)
        return deformed, extended

    def rigid(f: "_Fold") -> float | None:
        if cancel is not None and cancel.is_set():
            return None
        # the rigid answer fitted to the same training data (τ, θ alone; a kept pose stays); its
        # LM steps read only the pose columns of the shared start's Jacobian
        pose = zero if not options.pose else register_libr(model, f.train, None, replace(fold, deform=False), None,
                                                           cancel, first=first(f)).beta
        return pooled_rms(evaluate(model, f.held, pose, options.weights, jacobian=False).features, f.held)

    # the folds' fits are independent: on two cores the deformable ones first (the longest), the
    # rigid ones after; each the same computation as alone, gathered in fold order
    # (docs/decisions/speed.md, "The folds on both cores")
    threads = fresh_threads()
    if lead is not None and beside is not None:
        lead, beside = _after(lead, beside)
    # (deformable?, block), or None: the caller's ``beside``; a block whose fold has no training or
    # no held-out points (``prepared``) is skipped
    tasks: list[tuple[bool, int] | None]
    blocks = range(support.blocks)
    if threads > 1:
        tasks = [*((True, b) for b in blocks), *([None] if beside is not None else []), *((False, b) for b in blocks)]
    else:  # as before: each fold's deformable fit, then its rigid one
        tasks = [(job, b) for b in blocks for job in (True, False)]
    fitted: dict[int, tuple[float, float] | None] = {}  # block → deformable RMS (today's model, extended)
    fixed: dict[int, float | None] = {}  # block → rigid RMS

    def run(i: int) -> None:
        task = tasks[i]
        if task is None:
            assert beside is not None
            beside()
            return
        f = prepared()[2].get(task[1])
        if f is None:
            return
        if task[0]:
            fitted[f.block] = deformable(f)
        else:
            fixed[f.block] = rigid(f)

    in_threads(run, len(tasks), threads, lead=lead)
    folds = list(prepared()[2].values())
    out, out_ext = [], []
    for f in folds:
        d, r = fitted[f.block], fixed[f.block]
        if d is None or r is None:
            return None
        pts = np.vstack(list(f.held.values()))
        out.append(Block(pts.mean(0), len(pts), r, d[0]))
        out_ext.append(Block(pts.mean(0), len(pts), r, d[1]))
    if not out or (cancel is not None and cancel.is_set()):
        return None  # cut short: folds stopped before they were fitted say nothing about the data
    margin, paired = verdict_rule(data, support)
    sec = time.perf_counter() - t0
    # what a held-out RMS can resolve: the standard error of a mean over the held-out points at the
    # features' stated noise (the least of them), so that noise-free data on the undeformed model
    # (every block 10⁻⁹ mm either way) do not decide by rounding
    total = sum(b.points for b in out)
    noise = min((EXPECTED_NOISE_MM.get(k, 1.0) for k in data if k != "fiducials"), default=1.0)
    floor = noise / math.sqrt(max(total, 1))
    return _summary(out, margin, sec, paired, floor), _summary(out_ext, margin, sec, paired, floor)


@dataclass
class _Fold:
    """One fold of the cross-validation: its block, training and held-out points (feature →
    (N, 3) mm), and its rows of the shared start (``points_of``), made by its first fit."""

    block: int
    train: dict
    held: dict
    first: Evaluation | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)


_sequential_folds = Before()


def sequential_folds() -> AbstractContextManager[None]:
    """Within it, the cross-validation's folds run one after another in this thread, each
    fold's deformable fit then its rigid one, as before they shared the cores, and so does the
    rest of a fresh registration that would share them (``fresh_threads``: the pose choice's
    trimmed fit after the multi-start search, the deformable fit before the folds): the benches'
    "before", and the tests that the concurrent parts give the same bits; process-wide."""
    return _sequential_folds.taken()


def fresh_threads() -> int:
    """The threads a fresh registration's independent parts run on (the folds, and in
    ``pipeline`` the trimmed fit beside the multi-start search and the deformable fit beside the
    folds): ``threads.task_threads()``, or one within ``sequential_folds``."""
    return 1 if _sequential_folds else task_threads()


def paired_gain(blocks: list[Block]) -> tuple[float, float]:
    """The deformation's held-out gain over the rigid answer and its standard error.

    Parameters
    ----------
    blocks : list of Block
        the cross-validation's B held-out blocks: points n_b, RMS r_b (rigid) and d_b
        (deformable), mm.

    Returns
    -------
    (gain, se) : (float, float)
        mm: ḡ = Σ p_b g_b with g_b = r_b − d_b and p_b = n_b / Σ n, and
        sqrt(B / (B − 1) Σ p_b² (g_b − ḡ)²), the gain paired block by block. Paired because the
        blocks differ in how hard they are to predict (one over the dent, one flat) far more than
        the two answers do on any one block (as ``forces.one_standard_error`` judges its λ).
    """
    p = np.array([b.points for b in blocks], float)
    p /= p.sum()
    g = np.array([b.rigid_mm - b.deformable_mm for b in blocks])
    gain = float(p @ g)
    n = len(blocks)
    return gain, float(np.sqrt(n / max(n - 1, 1) * np.sum(p ** 2 * (g - gain) ** 2)))


def verdict_rule(data: dict, support: SupportOptions) -> tuple[float, bool]:
    """How the cross-validation's verdict is reached on ``data`` (feature → points): the relative
    ``margin`` (``margin_interior`` where data lie inside the organ, which rule out a wrong
    interior behind a good surface fit), and whether the paired gain against its standard error
    decides in its place (``SupportOptions.surface_se``, surface data alone)."""
    inside = any(DATA_TO_MODEL[k] not in ("liver", "fiducials", *SALIENT) for k in data)
    return (support.margin_interior if inside else support.margin), support.surface_se and not inside


def _summary(blocks: list[Block], margin: float, seconds: float, paired: bool = False, floor: float = 0.0) -> Support:
    w = np.array([b.points for b in blocks], float)
    r = float(np.average([b.rigid_mm for b in blocks], weights=w))
    d = float(np.average([b.deformable_mm for b in blocks], weights=w))
    return Support(r, d, blocks, margin, seconds, se_mm=max(paired_gain(blocks)[1], floor), paired=paired)


def weigh_correction(model: RegistrationModel, data: dict, beta, support: Support, options: LMOptions,
                     settings: SupportOptions = SupportOptions()) -> Support:
    """``support`` with the correction of a fit from a kept pose weighed against its σ
    (module doc): the mean over every n-th mesh node (``settings.sample_nodes`` of them) of
    |x(β) − x| and of σ = sqrt(tr(G Σ_β Gᵀ)) (``uncertainty``), mm. ``data``: feature →
    (N, 3) mm in the model frame; ``beta`` (3k + 6,) the fit's."""
    t0 = time.perf_counter()
    nodes = np.arange(0, model.basis.M, max(1, model.basis.M // settings.sample_nodes))
    with limit_threads(1):  # small matrices: threaded BLAS only synchronises (see libr.py)
        info = information(model, data, beta, options.weights)
        x, G = point_jacobian(model, beta, nodes=nodes)
        sigma = point_sigma(G, factor=covariance_factor(info))
    moved = np.linalg.norm(x - model.basis.nodes[nodes], axis=1)
    return replace(support, correction_mm=float(moved.mean()), sigma_mm=float(sigma.mean()), z=settings.z,
                   z_strong=settings.z_strong, seconds=support.seconds + time.perf_counter() - t0)


@dataclass
class TargetSupport:
    """Whether one target's correction is determined by the data."""
    name: str
    nearest_data_mm: float
    block_supported: bool | None  # the verdict of the held-out block nearest the target
    # the caller's words for "at the last full registration" when the block verdicts are a fresh
    # registration's carried to a warm start or a live frame, which does not cross-validate
    said: str | None = None

    @property
    def determined(self) -> bool:
        return self.nearest_data_mm <= SupportOptions.far_mm and self.block_supported is not False

    @property
    def warning(self) -> FitWarning | None:
        """The target's line (``WarningKind.TARGET``); one that rests on a carried block verdict
        (not on the distance, which this answer's own data give) ends with `` (said)`` and is
        marked ``carried``, as ``pipeline.Registration.carry`` marks the answer's lines."""
        if self.determined:
            return None
        if self.nearest_data_mm > SupportOptions.far_mm:
            why = f"no data within {SupportOptions.far_mm:g} mm (nearest {self.nearest_data_mm:.0f} mm)"
            return FitWarning(WarningKind.TARGET, f"deformation not determined by the data near {self.name}: {why}")
        line = (f"deformation not determined by the data near {self.name}: the data around it are not "
                f"predicted better by the deformation than without it")
        if self.said:
            return FitWarning(WarningKind.TARGET, f"{line} ({self.said})", carried=True)
        return FitWarning(WarningKind.TARGET, line)


def target_support(support: Support | None, centres: dict, data: dict,
                   said: str | None = None) -> list[TargetSupport]:
    """Per target (name → (3,) mm in the model frame): its nearest data point and the
    verdict of the nearest held-out block (None without cross-validation). ``said``: the
    caller's words for "at the last full registration" when ``support`` is the fresh
    registration's that a warm one continues from (``TargetSupport.said``)."""
    pts = np.vstack([p for p in data.values() if len(p)]) if data else np.zeros((0, 3))
    tree = cKDTree(pts) if len(pts) else None
    out = []
    for name, c in centres.items():
        near = float(tree.query(c)[0]) if tree is not None else float("inf")
        verdict = None
        if support is not None and support.blocks:
            b = min(support.blocks, key=lambda b: float(np.linalg.norm(b.centre - c)))
            verdict = b.supported
        out.append(TargetSupport(name, near, verdict, said))
    return out
