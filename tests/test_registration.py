import ast
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from navapp.registration.libr import LMOptions, register_libr
from navapp.registration.objective import Weights, evaluate
from navapp.registration.pipeline import deform_points, register
from navapp.registration.rotation import rotation, rotation_derivatives


def synthetic_data(model, alpha, rng, theta=(0, 0, 0), tau=(0, 0, 0)):
    """Points on the model deformed by β = (α, τ, θ): one set per kind of feature."""
    beta = np.concatenate([alpha, tau, theta])
    u = (model.basis.Ju @ alpha).reshape(-1, 3)
    R, c = rotation(np.asarray(theta, float)), model.centroid
    out = {}
    for name, feat, count in (("anterior", "liver", 150), ("portal_contour", "portal", 60),
                              ("portal_centerline", "portal_centerline", 20), ("fiducials", "fiducials", None)):
        f = model.features[feat]
        X = (f.rest + f.B @ u - c) @ R.T + np.asarray(tau) + c
        idx = np.arange(len(X)) if count is None else rng.choice(len(X), count, replace=False)
        out[name] = X[idx]
    return out, beta


def test_lm_solve_is_scipys_positive_definite_solve_to_the_bit_with_its_fallback():
    """``libr._solve`` calls LAPACK's posv and pocon itself: the same step as
    ``scipy.linalg.solve(assume_a="pos")`` on LM's damped normal matrices, and least squares
    where SciPy's solve refuses (not positive definite) or warns (rcond below machine ε)."""
    import warnings

    import scipy.linalg as sla

    from navapp.registration.libr import _solve

    rng = np.random.default_rng(3)
    for _ in range(20):
        J = rng.normal(size=(400, 141)) * rng.uniform(1e-3, 1e2, 141)
        A = J.T @ J
        A += 1e-2 * np.diag(np.diag(A))
        g = rng.normal(size=141)
        assert np.array_equal(_solve(A, g), sla.solve(A, g, assume_a="pos", check_finite=False))
    g = np.ones(3)
    for A in (np.diag([1.0, 1.0, 0.0]), np.diag([1.0, 1.0, 1e-17]), np.array([[1.0, 2, 0], [2, 1, 0], [0, 0, 1]])):
        with warnings.catch_warnings():
            warnings.simplefilter("error", sla.LinAlgWarning)
            with pytest.raises((sla.LinAlgError, sla.LinAlgWarning)):
                sla.solve(A, g, assume_a="pos", check_finite=False)
        assert np.array_equal(_solve(A, g), sla.lstsq(A, g, check_finite=False)[0])
    A = np.diag([1.0, 1.0, 1e-15])  # rcond just above ε: solved, not least squares
    assert np.array_equal(_solve(A, g), sla.solve(A, g, assume_a="pos", check_finite=False))


def test_rotation_derivatives_match_finite_differences():
    th = np.array([0.3, -0.2, 0.5])
    D = rotation_derivatives(th)
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1e-6
        assert np.allclose((rotation(th + e) - rotation(th - e)) / 2e-6, D[j], atol=1e-8)


def test_jacobian_matches_central_differences(small_model):
    """Table I against finite differences, every feature kind and the energy term, with
    the iteration's correspondences (normals, tangents) held fixed as the method does."""
    rng = np.random.default_rng(1)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n) * 0.3, rng)
    data = {k: v + rng.normal(size=v.shape) * 1.5 for k, v in data.items()}
    beta = np.concatenate([rng.normal(size=n) * 0.2, [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    w = Weights()
    ev = evaluate(small_model, data, beta, w)
    h = 1e-6
    J = np.zeros_like(ev.J)
    for j in range(n + 6):
        e = np.zeros_like(beta)
        e[j] = h
        fp = evaluate(small_model, data, beta + e, w, False, frozen=ev.correspondence).f
        fm = evaluate(small_model, data, beta - e, w, False, frozen=ev.correspondence).f
        J[:, j] = (fp - fm) / (2 * h)
    scale = np.abs(ev.J).max(axis=1, keepdims=True) + 1e-30
    assert np.all(np.abs(J - ev.J) <= 1e-6 * scale)


def test_objective_is_unit_invariant(small_model):
    """Ω in mm with weights converted equals Ω of the same state in metres (SI)."""
    rng = np.random.default_rng(2)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n) * 0.3, rng)
    data = {k: v + rng.normal(size=v.shape) for k, v in data.items()}
    beta = np.concatenate([rng.normal(size=n) * 0.2, [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    om_mm = evaluate(small_model, data, beta, Weights()).omega
    b = small_model.basis
    b_m = replace(b, nodes=b.nodes * 1e-3, Ju=b.Ju * 1e-3)  # strain and stress (Pa) unchanged
    feats = {k: replace(f, rest=f.rest * 1e-3, BJ=f.BJ * 1e-3) for k, f in small_model.features.items()}
    model_m = replace(small_model, basis=b_m, features=feats, centroid=small_model.centroid * 1e-3)
    beta_m = beta.copy()
    beta_m[n:n + 3] *= 1e-3
    om_m = evaluate(model_m, {k: v * 1e-3 for k, v in data.items()}, beta_m, Weights(unit_m=1.0)).omega
    assert np.isclose(om_mm, om_m, rtol=1e-10)


def test_recovers_a_deformation_in_the_basis(small_model):
    rng = np.random.default_rng(3)
    n = small_model.basis.Ju.shape[1]
    alpha = np.zeros(n)
    alpha[rng.choice(n, 6, replace=False)] = rng.normal(size=6)
    data, beta_true = synthetic_data(small_model, alpha, rng, theta=(0.02, -0.01, 0.015), tau=(2.0, -1.0, 1.5))
    data.pop("fiducials")
    w = Weights(energy=0.0)  # no regulariser: the exact state is the unique minimiser
    res = register_libr(small_model, data, options=LMOptions(weights=w, max_iterations=200))
    nodes = small_model.basis.nodes
    truth = deform_points(small_model.basis, small_model.centroid, beta_true, nodes)
    fit = deform_points(small_model.basis, small_model.centroid, res.beta, nodes)
    assert np.linalg.norm(fit - truth, axis=1).max() < 0.05, res.stop_reason
    assert res.stop_reason in ("converged", "stationary")


def test_rigid_icp_recovers_pose(small_model):
    rng = np.random.default_rng(4)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, np.zeros(n), rng)
    R = rotation(np.radians([8.0, -6.0, 10.0]))
    t = np.array([5.0, -3.0, 4.0])
    c = small_model.centroid
    moved = {k: (v - c) @ R.T + c + t for k, v in data.items() if k != "fiducials"}
    reg = register(small_model, moved, deform=False)
    probe = small_model.basis.nodes
    assert np.linalg.norm(reg.rigid.apply(probe) - ((probe - c) @ R.T + c + t), axis=1).max() < 0.2


def test_bit_identical_repeats(small_model):
    rng = np.random.default_rng(6)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n) * 0.5, rng)
    a = register(small_model, data)
    b = register(small_model, {k: v.copy() for k, v in data.items()})
    assert np.array_equal(a.libr.beta, b.libr.beta) and a.libr.omega == b.libr.omega


def test_progress_callback_and_cancel(small_model):
    import threading

    rng = np.random.default_rng(7)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n), rng)
    seen = []
    cancel = threading.Event()

    def cb(p):
        seen.append(p)
        if p.iteration == 3:
            cancel.set()

    res = register_libr(small_model, data, callback=cb, cancel=cancel)
    assert res.stop_reason == "cancelled" and res.iterations == 3
    assert [p.iteration for p in seen] == [1, 2, 3]
    assert all(np.isfinite(p.omega) and p.elapsed >= 0 for p in seen)
    warm = register_libr(small_model, data, beta0=res.beta)
    # a warm start begins where the cancelled run stopped (an ignored β0 would begin at its start)
    assert warm.history[0] == pytest.approx(res.history[-1], rel=1e-9) and warm.history[0] < res.history[0]


def test_a_cancel_after_the_fit_during_its_cross_validation_cancels_the_registration(small_model, monkeypatch):
    """A Cancel that arrives after LM has converged, while the deformation is cross-validated
    (in the viewer: a click a second after the start), stops the registration: the answer is
    reported cancelled (the viewer keeps the previous result, as it tells the surgeon) and no
    verdict is drawn from folds stopped before they were fitted. Before, the run was reported
    finished and replaced the previous result, and the cut-short folds (β = 0) made a verdict."""
    import threading

    import navapp.registration.pipeline as pipeline
    from navapp.registration.support import check_support

    rng = np.random.default_rng(8)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n), rng)
    cancel = threading.Event()
    verdicts = []

    def clicked_during_the_check(*args, lead=None, **kwargs):
        if lead is None:
            cancel.set()
        else:  # the fit runs beside the folds (two cores): the click comes once it has finished
            fit = lead

            def lead():
                fit()
                cancel.set()
        verdicts.append(check_support(*args, lead=lead, **kwargs))
        return verdicts[-1]

    monkeypatch.setattr(pipeline, "check_support", clicked_during_the_check)
    reg = register(small_model, data, cancel=cancel)
    assert verdicts == [None] and reg.support is None
    assert reg.libr.stop_reason == "cancelled" and reg.libr.iterations > 0  # LM itself had finished
    monkeypatch.undo()
    assert register(small_model, data).support is not None  # the same data, not cancelled: a verdict


def test_held_correspondences_fast_path_equals_full_deformation(small_model):
    """Ω with correspondences held fixed, from S·B·J_u (fast path) and from deforming
    every model point and applying S (reference), at a state far from the one that
    made the correspondences."""
    rng = np.random.default_rng(11)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n) * 0.5, rng)
    beta0 = np.concatenate([rng.normal(size=n) * 0.2, [1.0, -2.0, 0.5], np.radians([3.0, -2.0, 4.0])])
    ev = evaluate(small_model, data, beta0, Weights())
    assert all(c.carries_basis for c in ev.correspondence.values())
    beta1 = beta0 + np.concatenate([rng.normal(size=n) * 0.3, [0.5, 0.5, -1.0], np.radians([-2.0, 1.0, 1.0])])
    fast = evaluate(small_model, data, beta1, Weights(), jacobian=False, frozen=ev.correspondence)
    slow = evaluate(small_model, data, beta1, Weights(), jacobian=False,
                    frozen={k: c.without_basis() for k, c in ev.correspondence.items()})
    # the full deformation multiplies B·J_u in single precision (``model.displacement``), the
    # fast path S·B·J_u in double: they agree to that rounding, ~1e-7 mm here
    assert np.allclose(fast.f, slow.f, rtol=0, atol=1e-5)
    assert np.isclose(fast.omega, slow.omega, rtol=1e-6)


def test_single_precision_deformation_stays_within_a_micrometre(small_model):
    """Eq. 8 at every model feature, J_u α from B·J_u in single precision
    (``RegistrationModel.positions``), against the double-precision product, at a deformation
    larger than any fit reaches (‖α‖ ≈ 60: the demo's fits end near 25)."""
    from navapp.registration.model import deform, displacement

    rng = np.random.default_rng(5)
    n = small_model.basis.Ju.shape[1]
    beta = np.concatenate([rng.normal(size=n) * 60 / np.sqrt(n), [3.0, -1.0, 2.0], np.radians([5.0, -4.0, 3.0])])
    for feat in small_model.features.values():
        u = displacement(feat.BJ, beta[:n])
        assert np.abs(u).max() > 1.0  # a real deformation (mm)
        _, exact = deform(feat.rest, u, beta, small_model.centroid)
        _, x = small_model.positions(feat, beta)
        assert feat.single_basis().dtype == np.float32
        assert np.abs(x - exact).max() < 1e-3  # mm


def test_component_residuals_are_table_one_distances_with_an_exact_linear_model(small_model):
    """Centerline and fiducial terms enter LM as the components of (I − ttᵀ)p and of p.
    Per point, their norm must be Table I's f = sqrt(pᵀp − (pᵀt)²) (resp. ‖p‖); and with
    correspondences and rotation held, a step in α and τ must change them exactly as the
    Jacobian predicts (the scalar norm form only matches to first order)."""
    rng = np.random.default_rng(12)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n) * 0.3, rng)
    data = {k: data[k] + rng.normal(size=data[k].shape) for k in ("portal_centerline", "fiducials")}
    beta = np.concatenate([rng.normal(size=n) * 0.2, [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    ev = evaluate(small_model, data, beta, Weights())
    held = {k: c.without_basis() for k, c in ev.correspondence.items()}
    full = evaluate(small_model, data, beta, Weights(), jacobian=False, frozen=held)
    x = {k: c.S @ small_model.positions(small_model.feature_for(k), beta)[1] for k, c in held.items()}
    p = data["portal_centerline"] - x["portal_centerline"]
    t = held["portal_centerline"].direction
    f_cl = np.sqrt(np.einsum("ij,ij->i", p, p) - np.einsum("ij,ij->i", p, t) ** 2)
    f_fid = np.linalg.norm(data["fiducials"] - x["fiducials"], axis=1)
    assert np.isclose(full.features["portal_centerline"]["rms_mm"], np.sqrt(np.mean(f_cl ** 2)), rtol=1e-12)
    assert np.isclose(full.features["fiducials"]["max_abs_mm"], f_fid.max(), rtol=1e-12)
    step = np.concatenate([rng.normal(size=n) * 0.5, [2.0, -1.0, 1.5], [0.0, 0.0, 0.0]])
    moved = evaluate(small_model, data, beta + step, Weights(), jacobian=False, frozen=ev.correspondence)
    lin = ev.f + ev.J @ step
    # exact but for rounding: ev.f from the whole deformation (J_u α in single precision,
    # ``model.displacement``), moved.f from the held S·B·J_u in double; the norm form's
    # first-order error here is ~1e-2 mm
    assert np.allclose(moved.f[:-1], lin[:-1], rtol=0, atol=1e-5)


def test_jacobian_added_later_equals_jacobian_at_once(small_model):
    """LM evaluates an accepted state without its Jacobian and adds it only if it goes on;
    that must give exactly the Jacobian and held correspondences of a direct evaluation."""
    from navapp.registration.objective import add_jacobian

    rng = np.random.default_rng(13)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n) * 0.3, rng)
    beta = np.concatenate([rng.normal(size=n) * 0.2, [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    now = evaluate(small_model, data, beta, Weights())
    later = evaluate(small_model, data, beta, Weights(), jacobian=False)
    assert later.J is None and not any(c.carries_basis for c in later.correspondence.values())
    add_jacobian(small_model, later)
    assert np.array_equal(now.J, later.J) and now.omega == later.omega
    for k, c in now.correspondence.items():
        d = later.correspondence[k]
        assert c.S.same(d.S)
        assert all(np.array_equal(a, b) for a, b in ((c.direction, d.direction), (c.SBJ, d.SBJ), (c.S_rest, d.S_rest))
                   if a is not None)


def test_compiled_jacobian_equals_scipy_numpy_to_the_bit(small_model):
    """The compiled α columns (``jacobian_compiled``) give the Jacobian of the SciPy/NumPy
    formation bit for bit, and its held S·B·J_u rounded to single precision, on every feature
    kind (one row per surface point, three per centerline point and fiducial)."""
    from navapp.registration.jacobian_compiled import alpha_columns
    from navapp.registration.objective import add_jacobian, numpy_jacobian

    if alpha_columns is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(17)
    n = small_model.basis.Ju.shape[1]
    data, _ = synthetic_data(small_model, rng.normal(size=n) * 0.3, rng)
    data = {k: v + rng.normal(size=v.shape) for k, v in data.items()}
    beta = np.concatenate([rng.normal(size=n) * 0.2, [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    compiled = add_jacobian(small_model, evaluate(small_model, data, beta, Weights(), jacobian=False))
    with numpy_jacobian():
        reference = add_jacobian(small_model, evaluate(small_model, data, beta, Weights(), jacobian=False))
    assert np.array_equal(compiled.J, reference.J)
    assert np.array_equal(compiled.Js, reference.J * np.sqrt(reference.w)[:, None])  # √W·J made beside J
    assert np.array_equal(compiled.f, reference.f)  # S·X compiled, in SciPy's order
    for k, c in compiled.correspondence.items():
        assert c.SBJ.dtype == np.float32 and np.array_equal(c.SBJ, reference.correspondence[k].SBJ.astype(np.float32))
        assert np.array_equal(c.S_rest, reference.correspondence[k].S_rest)


def test_regions_deformed_as_rows_of_the_liver_give_the_same_evaluation(small_model):
    """A labelled region's points are rows of the liver surface's: an evaluation takes them from
    the liver's deformation (``ModelFeature.part_of``). Against each region deformed by its own
    B·J_u: the same points (to rounding: BLAS sums a row as it likes), the same Ω and Jacobian."""
    from dataclasses import replace as swap

    from navapp.registration.model import RegistrationModel

    regions = [k for k, f in small_model.features.items() if f.part_of == "liver"]
    assert regions, "the phantom's model has labelled regions"
    own = RegistrationModel(small_model.basis, {k: swap(f, part_of=None, part_rows=None) if k in regions else f
                                                for k, f in small_model.features.items()}, small_model.centroid)
    rng = np.random.default_rng(23)
    n = small_model.basis.Ju.shape[1]
    beta = np.concatenate([rng.normal(size=n) * 0.3, [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    liver = small_model.features["liver"]
    data = {"anterior": liver.rest[rng.choice(len(liver.rest), 80, replace=False)] + rng.normal(size=(80, 3))}
    for name in regions:
        f = small_model.features[name]
        assert np.array_equal(f.rest, liver.rest[f.part_rows]) and np.array_equal(f.BJ, liver.BJ[f.part_rows])
        data[name] = f.rest[rng.choice(len(f.rest), min(20, len(f.rest)), replace=False)] + rng.normal(size=(1, 3))
    a, b = evaluate(small_model, data, beta, Weights()), evaluate(own, data, beta, Weights())
    # J_u α in single precision (``model.displacement``): a row of the liver's product and the
    # region's own differ by its rounding (~1e-7 mm), not only in the last bit
    assert np.isclose(a.omega, b.omega, rtol=1e-6, atol=0)
    assert np.allclose(a.J, b.J, rtol=1e-6, atol=1e-9)
    # the same residuals to that rounding (a closest point on an edge may take either triangle
    # of it when the edge's two deformed copies differ by it)
    assert np.allclose(a.f, b.f, rtol=0, atol=1e-6)


def test_eq8_one_implementation_agrees_at_features_and_arbitrary_points(small_model):
    """model.positions (a feature's B·J_u), deform_points (interpolated in the mesh) and the
    held fast path (S·B·J_u) all go through registration.model.deform; at the liver surface
    nodes they must agree with eq. 8 written out here with scipy's rotation."""
    from scipy.spatial.transform import Rotation

    from navapp.registration.model import deform

    rng = np.random.default_rng(5)
    n = small_model.basis.Ju.shape[1]
    beta = np.concatenate([rng.normal(size=n) * 0.4, [2.0, -1.0, 3.0], np.radians([10.0, -7.0, 4.0])])
    feat = small_model.features["liver"]
    local, X = small_model.positions(feat, beta)
    # eq. 8 by hand: R(θ) = Rx Ry Rz (rotation.py), i.e. scipy's intrinsic "XYZ" angles
    R = Rotation.from_euler("XYZ", beta[n + 3:]).as_matrix()
    assert np.allclose(R, rotation(beta[n + 3:]), atol=1e-12)
    u = (small_model.basis.Ju @ beta[:n]).reshape(-1, 3)[small_model.basis.surface]
    by_hand = (feat.rest + u - small_model.centroid) @ R.T + beta[n:n + 3] + small_model.centroid
    assert np.allclose(X, by_hand, atol=1e-9)
    assert np.allclose(deform_points(small_model.basis, small_model.centroid, beta, feat.rest), by_hand, atol=1e-6)
    # positions' J_u α in single precision (``model.displacement``): its rounding, ~1e-6 mm
    assert np.allclose(deform(feat.rest, u, beta, small_model.centroid)[0], local, rtol=0, atol=1e-4)


def test_every_stop_reason_the_solver_returns_is_documented():
    """libr's docstring lists the stop reasons; "stationary" was returned but not listed."""
    import navapp.registration.libr as libr

    src = Path(libr.__file__).read_text()
    returned = {node.value.value for node in ast.walk(ast.parse(src))
                if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "reason" for t in node.targets)
                and isinstance(node.value, ast.Constant)}
    returned |= {"no_data"}  # returned directly, not through ``reason``
    assert returned <= set(libr.STOP_REASONS)
    for r in libr.STOP_REASONS:
        assert f'"{r}"' in libr.__doc__, r


def test_compiled_alpha_columns_take_rows_in_any_order_to_the_bit():
    """``jacobian_compiled.alpha_columns`` makes J's rows from each point's S·B·J_u summed in
    double precision, whether the rows come in point order (one pass) or not (summed again),
    while the S·B·J_u it keeps is single precision: J is the same bits either way."""
    from navapp.registration.jacobian_compiled import alpha_columns

    if alpha_columns is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(5)
    V, N, n = 40, 12, 9
    BJ = rng.normal(size=(V, 3, n)) * 7.3
    indptr = np.arange(0, 3 * N + 1, 3, dtype=np.int32)
    indices = rng.integers(0, V, 3 * N).astype(np.int32)
    weights = rng.random(3 * N)
    rows = np.repeat(np.arange(N), 3)  # three rows a point, as a centerline's or a fiducial's
    qR = rng.normal(size=(len(rows), 3))
    U = np.empty((N, 3, n), np.float32)
    J = np.empty((len(rows), n + 6))
    sw = rng.random(len(rows))
    Js = np.empty_like(J)
    alpha_columns(indptr, indices, weights, BJ, qR, rows, U, J, sw, Js)
    assert np.array_equal(Js[:, :n], J[:, :n] * sw[:, None])
    exact = np.einsum("ivak->iak", weights.reshape(N, 3)[:, :, None, None] * BJ[indices.reshape(N, 3)])
    assert np.array_equal(U, exact.astype(np.float32))
    shuffle = rng.permutation(len(rows))
    J2 = np.empty_like(J)
    alpha_columns(indptr, indices, weights, BJ, qR[shuffle], rows[shuffle], np.empty_like(U), J2, sw[shuffle],
                  np.empty_like(J))
    assert np.array_equal(J2[:, :n], J[shuffle, :n])
    # from the single-precision sums the rows would differ: the test can tell
    from_single = -np.einsum("ra,rak->rk", qR, U[rows].astype(float))
    assert not np.array_equal(from_single, J[:, :n])


def test_positions_compiled_are_eq8_of_the_single_precision_product(small_model):
    """``RegistrationModel.positions`` makes eq. 8 in one compiled pass (``deform_compiled``):
    every feature's local part the same bits as ``model.deform`` of the same single-precision
    product, x(β) within rounding of it, and at α = 0 ``deform``'s own answer."""
    from navapp.registration.model import deform, displacement

    rng = np.random.default_rng(29)
    n = small_model.basis.Ju.shape[1]
    beta = np.concatenate([rng.normal(size=n) * 0.3, [1.0, -2.0, 0.5], [0.05, -0.03, 0.04]])
    for name, feat in small_model.features.items():
        local, x = small_model.positions(feat, beta)
        ref_local, ref_x = deform(feat.rest, displacement(feat.BJ, beta[:n], feat.single_basis()), beta,
                                  small_model.centroid)
        assert np.array_equal(local, ref_local), name
        assert np.abs(x - ref_x).max() <= 1e-9, name
        rest = np.concatenate([np.zeros(n), beta[n:]])
        assert all(np.array_equal(a, b) for a, b in zip(small_model.positions(feat, rest),
                                                        deform(feat.rest, np.zeros_like(feat.rest), rest,
                                                               small_model.centroid), strict=True)), name


def test_a_registrations_stages_are_timed_in_the_order_they_run(small_model):
    """``Registration.stages`` (``pipeline._Registering``): the pose before the deformation, the
    deformation before its cross-validation and the organ's error, the coverage check last; a warm
    re-registration from the answer's state runs no cross-validation and no error estimate, and
    its pose is the one it was given."""
    from conftest import noisy_feature_data

    data = noisy_feature_data(small_model, np.random.default_rng(42))
    fresh = register(small_model, data)
    names = list(fresh.stages)
    assert names[-1] == "coverage"
    pose_end = max(names.index(n) for n in ("icp", "pose_choice", "determinacy"))
    deform_at = next(i for i, n in enumerate(names) if n.startswith("deformable"))
    assert pose_end < deform_at < names.index("support")
    if fresh.organ is not None:
        assert names.index("organ_error") > names.index("support")
    warm = register(small_model, data, beta0=fresh.libr.beta, rigid=fresh.rigid)
    assert "support" not in warm.stages and "organ_error" not in warm.stages
    np.testing.assert_array_equal(warm.rigid.R, fresh.rigid.R)
