"""Hard cases stay numerically stable: finite β and pose, a fit that never ends with a
larger Ω than it started from, and either a result or a typed error; and the table of
``navapp study hard`` (navapp/evaluation/hard.py) holds its stated bounds case by case."""

import numpy as np
import pytest

from navapp.errors import InputError
from navapp.registration.libr import LMOptions
from navapp.registration.objective import Weights
from navapp.registration.pipeline import register


def check(reg):
    r = reg.libr
    assert np.isfinite(r.beta).all() and np.isfinite(r.omega)
    assert np.isfinite(reg.rigid.R).all() and np.isfinite(reg.rigid.t).all()
    assert np.allclose(reg.rigid.R @ reg.rigid.R.T, np.eye(3), atol=1e-9)
    # the fit never ends worse than it started (Ω with correspondences recomputed, as
    # LibrResult.history records it), and each accepted step lowered Ω on its own
    # correspondences by a finite amount
    assert r.omega <= r.history[0] * (1 + 1e-9) + 1e-300
    assert all(np.isfinite(b) and np.isfinite(a) for b, a in r.steps)
    assert r.stop_reason in ("converged", "stationary", "max_iterations", "stalled", "no_data")
    return r


def surface_points(model, idx):
    return model.features["liver"].rest[idx]


def test_no_data(small_model):
    r = check(register(small_model, {}))
    assert r.stop_reason == "no_data" and not r.beta.any()


@pytest.mark.parametrize("count", [1, 2, 3])
def test_few_points(small_model, count):
    with pytest.warns(UserWarning, match="not determined"):
        check(register(small_model, {"anterior": surface_points(small_model, np.arange(count) * 7) + 1.0}))


def test_collinear(small_model):
    line = np.linspace([-40.0, 40.0, 0.0], [40.0, 40.0, 10.0], 30)
    with pytest.warns(UserWarning, match="one line"):
        check(register(small_model, {"anterior": line}))


def test_a_stylus_line_with_one_contour_point_on_each_vessel(small_model):
    """The live follower's first update that raised in CI (issue 48, item 5): a short line of
    digitised stylus points and a frame whose segmentation left one contour point on each
    vessel. The trimmed fit solved its six motions whole, so it stepped without bound along
    the ones such data leave free, until the pose stood ~1e221 mm off and the closest-point
    search read past its arrays (an IndexError, or the process crashed)."""
    from navapp.fitwarning import WarningKind
    from navapp.registration.pose import trimmed_pose
    from navapp.registration.rigid import RigidResult

    line = np.array([-17.601, 21.365, -27.552]) + np.outer(np.arange(10), [0.505, 0.203, -0.8005])
    data = {"anterior": line, "portal_contour": np.array([[-97.789, -13.645, 7.532]]),
            "hepatic_contour": np.array([[-63.944, -20.055, 21.058]])}
    pose, moved = trimmed_pose(small_model, data, RigidResult(np.eye(3), np.zeros(3), 0, 0.0))
    extent = float(np.ptp(small_model.basis.nodes, axis=0).max())
    assert np.isfinite(pose.t).all() and np.linalg.norm(pose.t) < extent and np.isfinite(moved)
    reg = register(small_model, data)
    check(reg)
    assert WarningKind.UNDETERMINED_POSE in {w.kind for w in reg.warnings}


def test_a_stroke_of_stylus_points_keeps_every_start_on_the_organ(small_model):
    """The live follower's first update raised the same IndexError in CI again (session 41):
    a stroke of stylus points leaves the point-to-plane steps of the multi-start ICP free to
    slide along the few vertex normals its points match. Iterated, starts stood 10⁶ mm off
    (5.8e6 on this stroke before the change), and the screening's searches read past their
    arrays. A step that carries the data's centre further out, beyond the organ's sphere,
    is undone and the start stops."""
    from navapp.registration.objective import robust_weights
    from navapp.registration.rigid import multi_start_icp, start_poses

    X = small_model.features["liver"].rest
    reach = np.linalg.norm(X - small_model.centroid, axis=1).max()
    rng = np.random.default_rng(0)
    top = X[X[:, 1] > np.percentile(X[:, 1], 70)]  # the anterior side, where a stylus strokes
    a, d = top[rng.integers(len(top))], rng.normal(size=3)
    d[1] = 0.0
    n = int(rng.integers(6, 20))
    line = a + np.outer(np.linspace(0.0, rng.uniform(10, 60), n), d / np.linalg.norm(d))
    from scipy.spatial import cKDTree

    line = X[cKDTree(X).query(line)[1]] + rng.normal(0.0, 0.3, (n, 3))
    data = {"anterior": line}
    starts = multi_start_icp(small_model, data, start_poses(small_model, data), robust_weights(1.0))
    for s in starts:
        centre = s.fitted.inverse(line).mean(0)
        assert np.linalg.norm(centre - small_model.centroid) <= reach, s.label
    check(register(small_model, data))


def test_coplanar(small_model):
    g = np.stack(np.meshgrid(np.linspace(-50, 50, 8), np.linspace(-30, 30, 8)), -1).reshape(-1, 2)
    check(register(small_model, {"anterior": np.column_stack([g[:, 0], np.full(len(g), 45.0), g[:, 1]])}))


def test_duplicated_points(small_model):
    p = surface_points(small_model, np.arange(0, 200, 10))
    check(register(small_model, {"anterior": np.vstack([p, p, p]) + 0.5}))


def test_point_exactly_on_centerline(small_model):
    """f = 0 for a centerline point, where Table I's scalar derivative is undefined: the
    component form (objective.residuals) must give a finite β and an exact fit."""
    cl = small_model.features["portal_centerline"].rest
    fid = small_model.features["fiducials"].rest
    r = check(register(small_model, {"portal_centerline": cl[:5], "fiducials": fid}, deform=True))
    assert r.omega < 1e-9


def test_far_away_data(small_model):
    p = surface_points(small_model, np.arange(0, 400, 4))
    check(register(small_model, {"anterior": p + np.array([50.0, 0.0, 0.0])}))


def test_twenty_degree_misalignment(small_model):
    from navapp.registration.rotation import rotation

    ant = small_model.features["liver"].rest
    c = small_model.centroid
    R = rotation(np.radians([20.0, 0.0, 0.0]))
    reg = register(small_model, {"anterior": (ant - c) @ R.T + c}, deform=True)
    check(reg)
    assert np.degrees(np.arccos(np.clip((np.trace(reg.rigid.R @ R.T) - 1) / 2, -1, 1))) < 1.0


def test_many_modes_small_patch(coarse_mesh, phantoms, cache_root):
    from navapp.mechanics.basis import BasisSettings, load_or_compute_basis
    from navapp.registration.model import build_model

    basis, _ = load_or_compute_basis(coarse_mesh, BasisSettings(k=90), cache_root=cache_root)
    model = build_model(basis, phantoms[0])
    patch = model.features["liver"].rest
    patch = patch[np.linalg.norm(patch - patch[np.argmax(patch[:, 1])], axis=1) < 25]
    check(register(model, {"anterior": patch + np.array([0.0, 2.0, 0.0])}))


@pytest.mark.parametrize("factor", [1e-6, 1e6])
def test_extreme_weights(small_model, factor):
    p = surface_points(small_model, np.arange(0, 300, 3))
    opts = LMOptions(weights=Weights().scaled(factor))
    check(register(small_model, {"anterior": p * 1.02}, options=opts))


def test_float32_input_equals_float64(small_model):
    p = (surface_points(small_model, np.arange(0, 300, 3)) * 1.02).astype(np.float32)
    a = check(register(small_model, {"anterior": p}))
    b = check(register(small_model, {"anterior": p.astype(np.float64)}))
    assert np.array_equal(a.beta, b.beta)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_input_rejected_before_solving(small_model, bad):
    p = surface_points(small_model, np.arange(10)).copy()
    p[3, 1] = bad
    with pytest.raises(InputError, match="NaN or infinite"):
        register(small_model, {"anterior": p})


# ---------------------------------------------------------------- the hard-case table


@pytest.fixture(scope="module")
def hard_setup(phantoms, cache_root):
    from navapp.evaluation.hard import make_setup

    return make_setup(phantoms[0], edge=12.0, k=12, cache_root=cache_root)  # the suite's 12 mm phantom mesh


@pytest.fixture(scope="module")
def hard_results(hard_setup):
    from navapp.evaluation.hard import run_hard

    return {r.case: r for r in run_hard(hard_setup)}


# Cases whose deformation exceeds the stated bound 2 d + 2 mm (docs/decisions/error-estimate.md, "Hard
# cases"): coplanar data ask little at their own points while the true bending elsewhere is
# larger (the fit finds it: TRE improves), collinear data fit anywhere along a wrong pose,
# and an almost unregularised fit bends where no data are. All stay within the energy
# bound the solver guarantees. Listed so that a change either way is seen.
EXCEEDS_STATED_BOUND = {"collinear", "coplanar", "soft"}
# Known defects the study shows since it judges the answer shown against navapp's own
# rigid-only answer and counts the lines the answer carries (docs/decisions/error-estimate.md, "Hard cases
# judged by the answer shown"), listed so that a change either way is seen (issue 46):
# - consistent data whose good answer (TRE better than rigid) still carries warnings: the
#   cross-validation's "deformation not supported" (held-out 0.92 against 1.26 mm at 12 mm: better,
#   but not by its 30 % margin). ICP's 5° / 11 mm correct move from the frame's identity, which the
#   fit earns (0.34 against 0.50 mm RMS, beyond ``PoseRule.given_ratio``), is no longer called "in
#   doubt" by a second line;
WARNED_ON_A_GOOD_ANSWER = {"baseline", "duplicated", "far", "weights x 1e-6", "weights x 1e6"}
# - answers worse than the rigid-only answer to the same data: the pose choice keeps the
#   data's own frame (identity, 11 mm / 5° off) over ICP's right pose; a pooled RMS dominated by
#   the contradictory points (3.95 against 3.96 mm), which no comparison of the two fits' residuals
#   and strain energy can overrule and still hold a pre-aligned scan over a deep dent
#   (docs/decisions/registration.md, "The undeclared pose choice: one line per decision, and what no summary of
#   the two fits can decide"). "90 deg" left this list when a basin turned beyond a tracker's error
#   was finished to convergence before the 45° turn rule judged it (81° with 43 % of the data
#   within 1 mm of the model, refused: 71.7 mm; converged 89°: 1.57 against 2.23 rigid-only).
WORSE_THAN_RIGID = {"contradictory"}
FAILING = EXCEEDS_STATED_BOUND | WARNED_ON_A_GOOD_ANSWER | WORSE_THAN_RIGID


def _case_names():
    from navapp.evaluation.hard import CASES

    return [c.name for c in CASES]


@pytest.mark.parametrize("name", _case_names())
def test_hard_case_within_its_bounds(hard_results, name):
    from navapp.evaluation.hard import CASES

    case = next(c for c in CASES if c.name == name)
    r = hard_results[name]
    if name in WARNED_ON_A_GOOD_ANSWER:
        assert r.outcome == "warned" and r.tre_mm < r.tre_rigid_mm, r
        # ... but not for its pose: ICP's move is earned by the fit (it was called "in doubt")
        assert "ICP's pose" not in r.message, r.message
    else:
        assert r.outcome in case.allowed, r.message
    assert r.identical  # bit-identical β, pose and TRE from the same input
    assert "\n" not in r.message
    if r.outcome == "refused":  # said, and nothing registered: no pose, no deformation, no error claimed
        assert r.message and r.iterations is None and r.raw_mm is None and r.tre_mm is None, r
        return
    assert r.raw_mm <= r.energy_bound_mm  # the guarantee: Ω never ends above its start
    if name in EXCEEDS_STATED_BOUND:
        assert r.displacement_mm > r.bound_mm
    else:
        assert r.displacement_mm <= r.bound_mm
    if name in WORSE_THAN_RIGID:
        assert r.tre_mm > r.tre_rigid_mm + case.margin_mm and r.outcome == "warned", r
    elif case.margin_mm is not None:
        assert r.tre_mm <= r.tre_rigid_mm + case.margin_mm
    assert r.iterations is not None and r.condition is not None and r.condition > 0
    others = [f for f in r.failures if not (("bound" in f and name in EXCEEDS_STATED_BOUND) or
                                            (f.startswith("outcome") and name in WARNED_ON_A_GOOD_ANSWER) or
                                            (f.startswith("TRE") and name in WORSE_THAN_RIGID))]
    assert not others


def test_far_data_frame_registers_like_the_aligned_one(hard_results):
    """A tracker frame 560 mm from the model's: the principal-axes start now matches the
    data to the model's vertices from the model's centroid (before: a wrong basin, TRE
    59.8 mm, flagged as a poor fit)."""
    base, far = hard_results["baseline"], hard_results["far"]
    assert far.outcome == base.outcome
    assert abs(far.tre_mm - base.tre_mm) < 0.05 and abs(far.tre_rigid_mm - base.tre_rigid_mm) < 0.05


def test_metres_read_as_millimetres_are_refused(hard_results):
    r = hard_results["metres as mm"]
    assert r.outcome == "refused" and "metres" in r.message and "millimetres" in r.message


@pytest.mark.parametrize("name", ["few", "collinear", "k >> data"])
def test_an_undetermined_pose_is_said(hard_results, name):
    """Data that cannot fix the rigid pose (registered silently before: TRE 50–98 mm)."""
    r = hard_results[name]
    assert r.outcome == "warned" and "not determined" in r.message
    assert r.condition > 1e5  # the LM system says the same


def test_condition_number_reported_only_when_asked(small_model):
    p = surface_points(small_model, np.arange(0, 300, 3)) * 1.02
    assert register(small_model, {"anterior": p}).libr.condition is None
    a = register(small_model, {"anterior": p}, options=LMOptions(condition=True)).libr
    b = register(small_model, {"anterior": p}).libr
    assert 1 < a.condition < 1e5  # well posed here; the undetermined poses above report > 1e5
    assert np.array_equal(a.beta, b.beta)  # asking for it changes nothing else


def test_undetermined_pose_rules():
    from navapp.registration.pipeline import undetermined_pose

    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(50, 3)) * 30
    line = np.linspace([0, 0, 0], [60, 10, 5], 20) + rng.normal(size=(20, 3)) * 0.01
    assert undetermined_pose({"anterior": cloud}) is None
    assert "5 data points" in undetermined_pose({"anterior": cloud[:5]})
    assert "one line" in undetermined_pose({"anterior": line})
    # three fiducials off a line fix the pose on their own
    assert undetermined_pose({"anterior": line, "fiducials": cloud[:3]}) is None
    assert undetermined_pose({}) is None


def test_energy_bound_against_random_states(small_model):
    """The energy bound holds for any α (not just the fitted ones): random α scaled to
    f_E = √(Ω₀ / w_E) never displace a node further than it says, and some come close."""
    from navapp.evaluation.hard import energy_bound

    basis = small_model.basis
    omega0, w = 2.5e-5, 1e-8
    bound = energy_bound(small_model, omega0, w)
    f_max = np.sqrt(omega0 / w)
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(200):
        a = rng.normal(size=basis.Ju.shape[1])
        a *= np.sqrt(f_max * 2 * basis.M / (a @ basis.energy @ a))
        worst = max(worst, np.linalg.norm((basis.Ju @ a).reshape(-1, 3), axis=1).max())
    assert worst <= bound and worst > 0.05 * bound


def test_study_hard_command(hard_setup, hard_results, tmp_path, monkeypatch, capsys):
    """``navapp study hard --edge 12 --k 12 --report DIR`` (README's command table): the
    model it asks for, the table printed, ``hard_cases.md`` written, exit 1 while a case
    breaks its stated bound. The table's registrations are this module's (the command runs
    ``run_hard`` on the same setup: computed once, not twice)."""
    from navapp.cli import main
    from navapp.evaluation import hard

    asked = []

    def setup(edge, k):
        asked.append((edge, k))
        return hard_setup

    monkeypatch.setattr(hard, "make_setup", setup)
    monkeypatch.setattr(hard, "run_hard", lambda s, on_result=None: [hard_results[c.name] for c in hard.CASES])
    code = main(["--quiet", "study", "hard", "--edge", "12", "--k", "12", "--report", str(tmp_path / "r")])
    out, err = capsys.readouterr()
    assert asked == [(12.0, 12)]
    assert code == (1 if FAILING else 0)
    lines = out.strip().splitlines()
    assert lines[0].split()[:2] == ["case", "outcome"] and len(lines) == 1 + len(hard.CASES)
    for line, case in zip(lines[1:], hard.CASES, strict=True):
        assert line.startswith(case.name)
        assert line.split()[-1] == ("FAIL" if case.name in FAILING else "ok"), line
    md = (tmp_path / "r" / "hard_cases.md").read_text()
    assert f"wrote {tmp_path / 'r' / 'hard_cases.md'}" in err
    n = len(hard.CASES)
    assert f"{n - len(FAILING)} of {n} cases within their bounds." in md
    assert "12 mm" in md and "`navapp study hard`" in md
    for name in FAILING:
        assert f"- {name}: " in md
