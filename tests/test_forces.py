"""Surface forces at every surface node (``registration.forces``): the adjoint gradient, the
supports, and a dent the k = 12 control-point basis cannot make."""

from dataclasses import replace

import numpy as np
import pytest

from navapp.mechanics.basis import BasisSettings, compute_basis


@pytest.fixture(scope="module")
def held_basis(coarse_mesh):
    return compute_basis(coarse_mesh, BasisSettings(k=12, supports="posterior"))


@pytest.fixture(scope="module")
def forces(held_basis):
    from navapp.registration.forces import SurfaceForces

    sf = SurfaceForces(held_basis)
    yield sf
    sf.close()


def _dent(basis, mesh, radius, depth, noise=0.0):
    """A tool ``radius`` mm pressed ``depth`` mm into the top of the posterior-held organ (its
    own linear response: ``simulation.truth``), seen at the anterior-facing surface nodes (y
    above its 60th percentile) with Gaussian noise of 3-D σ ``noise`` mm. Returns the true
    displacement (M, 3) and the points (N, 3)."""
    from navapp.mechanics.fem import Material
    from navapp.simulation.truth import Loading, Supports, Tool, ToolLoad, solve_linear

    s = basis.nodes[basis.surface]
    tool = Tool(tuple(s[np.argmax(s[:, 1])]), (0.0, -1.0, 0.0), radius, depth, ToolLoad.DISPLACEMENT)
    u_true = solve_linear(mesh, Loading(gravity=0.0, supports=Supports.POSTERIOR, tool=tool), Material()).reshape(-1, 3)
    scan = basis.surface[s[:, 1] > np.percentile(s[:, 1], 60)]
    pts = basis.nodes[scan] + u_true[scan]
    if noise:
        pts = pts + np.random.default_rng(3).normal(scale=noise / np.sqrt(3), size=pts.shape)
    return u_true, pts


def _scan(basis):
    """The anterior-facing surface nodes (y above its 60th percentile), (N, 3)."""
    s = basis.nodes[basis.surface]
    return s[s[:, 1] > np.percentile(s[:, 1], 60)]


def test_the_adjoint_gradient_matches_finite_differences(forces, held_basis):
    rng = np.random.default_rng(0)
    pts = _scan(held_basis) + rng.normal(scale=1.0, size=(len(_scan(held_basis)), 3))
    f = rng.normal(scale=50.0, size=3 * len(forces.surface))
    A, nrm, c = forces.correspondences(pts, forces.displacement(f.reshape(-1, 3)))
    phi, grad = forces.objective(f, A, nrm, c, 0.3)
    for j in rng.choice(len(f), 8, replace=False):
        h = 1e-3 * max(1.0, abs(f[j]))
        e = np.zeros_like(f)
        e[j] = h
        fd = (forces.objective(f + e, A, nrm, c, 0.3)[0] - forces.objective(f - e, A, nrm, c, 0.3)[0]) / (2 * h)
        assert fd == pytest.approx(grad[j], rel=1e-5, abs=1e-12 * abs(phi))


def test_the_displacement_vanishes_at_the_supports(forces, held_basis):
    from navapp.anatomy.tets import TetMesh
    from navapp.mechanics.supports import held_nodes

    u = forces.displacement(np.random.default_rng(1).normal(size=(len(forces.surface), 3)))
    held = held_nodes(TetMesh(held_basis.nodes, held_basis.tets), "posterior")
    assert np.abs(u[held]).max() == 0.0 and np.abs(u).max() > 0


def test_a_dent_under_the_data_is_fitted_by_surface_forces(forces, held_basis, coarse_mesh):
    """A 15 mm dent of 25 mm radius pressed into the anterior surface of the posterior-held
    organ (the organ's own linear response to a tool: ``simulation.truth``), seen by points on
    the anterior surface: the surface forces fit the points to under half a millimetre and the
    nodes' displacement to within 0.6 of its mean (no correction: all of it). Measured 0.36 mm and
    0.32 of 0.60 mm; the tool drags the nodes along the surface, which no point-to-surface datum
    sees (the scan's own nodes are 0.68 mm off). The bound was half (0.28 measured) while the
    force sites' closest points were sought among interior nodes too, a fault that on this
    12 mm mesh moved the answer little and on the study's 4 mm livers left the fits at 1–3 mm RMS
    (``test_the_force_sites_lie_at_the_points_closest_surface_points``)."""
    from navapp.registration.forces import ForceOptions

    u_true, pts = _dent(held_basis, coarse_mesh, 25.0, 15.0)
    fit = forces.fit(pts, ForceOptions(energy_weight=0.1, sites=len(pts)))
    err = np.linalg.norm(fit.u - u_true, axis=1).mean()
    assert fit.rms_mm < 0.5 and err < 0.6 * np.linalg.norm(u_true, axis=1).mean()  # measured 0.36, 0.32 of 0.60


@pytest.mark.parametrize("radius, depth, noise, lam", [(25.0, 15.0, 0.0, 0.1), (20.0, 20.0, 0.5, 1e-2)],
                         ids=["15mm-dent", "4cm-dent-noisy"])
def test_the_force_fit_is_a_continuous_function_of_its_data(forces, held_basis, coarse_mesh, monkeypatch,
                                                            radius, depth, noise, lam):
    """The dents' fits with the data moved by 10⁻⁹ mm, and with the stiffness factorised by
    SuperLU in its own minimum-degree ordering instead of the default (PARDISO, or SuperLU with
    nested dissection), move the nodes' displacement, the RMS and the node error by under
    10⁻⁶ mm. The residual is the true point–surface distance (the normal at an edge or vertex
    is the distance field's gradient, ``geometry.closest.surface_normals``), so the fit is a
    continuous function of the data and of rounding: measured 3 × 10⁻⁹ – 3 × 10⁻⁸ mm, a gain of
    at most ~30 on the shift; 10⁻⁶ leaves room for a gain of 1000. With the face's own normal at
    an edge or vertex, a point there took the normal of whichever incident face won the tie,
    its distance jumped (by 0.09 mm at w = 0 for 6 of 293 points), and the nodes moved by up to
    0.53 mm (15 mm dent) and 4.1 mm (4 cm dent) (docs/decisions/local-loads.md)."""
    from navapp.mechanics import sparse
    from navapp.registration.forces import ForceOptions, SurfaceForces

    u_true, pts = _dent(held_basis, coarse_mesh, radius, depth, noise)
    options = ForceOptions(energy_weight=lam, sites=len(pts))
    base, moved = forces.fit(pts, options), forces.fit(pts + 1e-9, options)
    monkeypatch.setenv("NAVAPP_SOLVER", "superlu")
    monkeypatch.setattr(sparse, "nested_dissection", lambda A: None)  # SuperLU's minimum degree
    other = SurfaceForces(held_basis)
    try:
        reordered = other.fit(pts, options)
    finally:
        other.close()

    def err(f):
        return float(np.linalg.norm(f.u - u_true, axis=1).mean())

    for fit in (moved, reordered):
        assert np.abs(fit.u - base.u).max() < 1e-6
        assert abs(fit.rms_mm - base.rms_mm) < 1e-6 and abs(err(fit) - err(base)) < 1e-6


def test_the_force_sites_lie_at_the_points_closest_surface_points(forces, held_basis, coarse_mesh):
    """The correspondences the forces act at (``SurfaceForces.correspondences``, at the
    undeformed surface: ``responses``' sites and directions) are the exact closest points on the
    surface, for points pressed into the organ by a 40 mm dent as well as for points off it.
    Their nearest vertices were once sought among all the mesh's nodes, interior ones included,
    and a point inside the organ then matched a far vertex (on tool1-c 336 of 500 points, 39 mm
    off against 3.9: the sites' forces spanned 54 of 150 dimensions)."""
    import trimesh

    _, pts = _dent(held_basis, coarse_mesh, 20.0, 40.0)
    pts = np.vstack([pts, _scan(held_basis) + 3.0 * np.random.default_rng(4).normal(size=(len(_scan(held_basis)), 3))])
    _, _, c = forces.correspondences(pts, np.zeros_like(held_basis.nodes))
    surface = trimesh.Trimesh(held_basis.nodes, held_basis.surface_faces, process=False)
    exact = trimesh.proximity.closest_point(surface, pts)[1]
    assert np.abs(np.abs(c) - exact).max() < 1e-6


def test_the_data_space_solve_is_the_minimiser_the_adjoint_gradient_finds(forces, held_basis):
    """One round at fixed correspondences: the forces ``fit`` solves for in the data's own space
    make Φ's adjoint gradient vanish (to a millionth of its size at f = 0)."""
    from navapp.registration.forces import ForceOptions

    rng = np.random.default_rng(2)
    pts = _scan(held_basis) + rng.normal(scale=2.0, size=(len(_scan(held_basis)), 3))
    lam = 0.05
    fit = forces.fit(pts, ForceOptions(energy_weight=lam, iterations=1, sites=len(pts)))
    A, nrm, c = forces.correspondences(pts, np.zeros((forces.M, 3)))
    _, g0 = forces.objective(np.zeros(3 * len(forces.surface)), A, nrm, c, lam)
    _, g = forces.objective(fit.f.ravel(), A, nrm, c, lam)
    assert np.linalg.norm(g) < 1e-6 * np.linalg.norm(g0)


def test_a_4cm_dent_the_k45_basis_cannot_fit_is_fitted_by_surface_forces_within_the_noise(coarse_mesh, phantoms):
    """The issue's test: a dent 4 cm across and 20 mm deep pressed into the posterior-held
    organ, seen by the anterior surface with noise of σ 0.29 mm along the normal (0.5 mm in
    3-D). LIBR with the k = 45 basis held at the same supports leaves its residual at over
    twice the noise (measured 0.80 mm); the surface forces fit the points within it (measured
    0.24 mm)."""
    from navapp.registration.forces import ForceOptions, SurfaceForces
    from navapp.registration.libr import LMOptions, register_libr
    from navapp.registration.model import build_model

    basis = compute_basis(coarse_mesh, BasisSettings(k=45, supports="posterior"))
    u_true, pts = _dent(basis, coarse_mesh, 20.0, 20.0, noise=0.5)
    sigma = 0.5 / np.sqrt(3)  # per axis: σ along the normal
    libr = register_libr(build_model(basis, phantoms[0], fiducials=basis.nodes[:6]), {"anterior": pts}, None,
                         LMOptions())
    sf = SurfaceForces(basis)
    try:
        fit = sf.fit(pts, ForceOptions(energy_weight=1e-2, sites=len(pts)))
    finally:
        sf.close()
    assert libr.features["anterior"]["rms_mm"] > 2 * sigma  # the k = 45 basis cannot make the dent
    assert fit.rms_mm < sigma  # the forces fit it within the noise


def _offset(points, q, centroid):
    """``points`` (N, 3) moved by the rigid part q = (τ mm, θ rad) of eq. 8 about ``centroid``."""
    from navapp.registration.rigid import beta_pose

    return beta_pose(q, centroid).apply(points)


def test_the_pose_jacobian_matches_finite_differences(forces, held_basis):
    """−∂d/∂q of the data's signed distances to the posed, deformed surface (``PoseTerm.jacobian``)
    against central differences of the distances themselves, away from q = 0."""
    from navapp.registration.forces import PoseTerm
    from navapp.registration.prior import PosePrior

    rng = np.random.default_rng(7)
    centroid = held_basis.nodes.mean(0)
    term = PoseTerm.of(PosePrior(5.0, 5.0), centroid)
    us = 0.5 * rng.normal(size=3 * len(forces.all_surface))
    pts = _scan(held_basis) + rng.normal(scale=1.0, size=(len(_scan(held_basis)), 3))
    q = np.array([1.0, -2.0, 0.5, 0.03, -0.02, 0.04])

    def dist(qq):
        return forces.distances(term.to_model(pts, qq)[0], us)

    d, _, nrm = dist(q)
    J = term.jacobian(term.to_model(pts, q)[0], d, nrm, q)
    for j in range(6):
        h = 1e-5
        e = np.zeros(6)
        e[j] = h
        fd = (dist(q + e)[0] - dist(q - e)[0]) / (2 * h)
        ok = np.isclose(-fd, J[:, j], rtol=1e-4, atol=1e-6 * np.abs(J[:, j]).max())
        # the distance is not differentiable where the closest point jumps (a concave edge's two
        # faces): a point or two of the scan may sit within h of such a place
        assert ok.mean() > 0.99


def test_a_tracker_offset_is_fitted_with_the_forces_under_the_declared_prior(forces, held_basis, coarse_mesh):
    """A 15 mm dent seen in a frame offset by 4.1 mm and 2.9° (the given pose that far off, declared
    to within 5 mm / 5°): the forces deforming from the given pose make the offset into a
    deformation and leave the organ's nodes 3.3 mm off (measured, λ = 1); fitted with the rigid
    part of eq. 8 under the prior they recover most of the offset and the nodes to within 1 mm
    (measured 0.80; 0.38 with the true pose given)."""
    from navapp.registration.forces import PoseTerm
    from navapp.registration.prior import PosePrior

    u_true, pts = _dent(held_basis, coarse_mesh, 25.0, 15.0, noise=0.5)
    centroid = held_basis.nodes.mean(0)
    q_true = np.array([2.0, -3.0, 2.0, np.radians(2.0), np.radians(-1.5), np.radians(1.5)])
    seen = _offset(pts, q_true, centroid)
    truth = _offset(held_basis.nodes + u_true, q_true, centroid)
    pf = forces.responses(seen)
    err = {}
    # σ_F as ``register`` settles it: the data's robust spread about the fit, here the noise along the normal
    prior = PosePrior(5.0, 5.0, feature_sd_mm=0.3)
    for name, pose in (("given", None), ("fitted", PoseTerm.of(prior, centroid))):
        wf = forces.fit_weights(pf, 1.0, pose=pose)
        moved = held_basis.nodes + forces.field(pf, wf)
        if wf.q is not None:
            moved = _offset(moved, wf.q, centroid)
        err[name] = float(np.linalg.norm(moved - truth, axis=1).mean())
    assert err["fitted"] < 1.0 and err["fitted"] < 0.5 * err["given"]


def test_no_deformation_is_chosen_where_forces_predict_held_out_data_worse(forces, held_basis):
    """Noise alone (3 mm along the normal) about the undeformed surface and only weak
    regularisers: every fit of forces predicts the held-out blocks worse than not deforming,
    and the choice is no deformation, with its line (without that candidate it would be the
    forces)."""
    from navapp.registration.forces import Answer, choose_deformation

    scan = _scan(held_basis)
    _, nrm, _ = forces.correspondences(scan, np.zeros((forces.M, 3)))
    pts = scan + np.random.default_rng(5).normal(scale=3.0, size=len(scan))[:, None] * nrm
    choice = choose_deformation(forces, None, {"anterior": pts}, None, None, weights=(1e-3, 1e-2))
    assert min(choice.forces_mm.values()) > choice.none_mm
    assert choice.answer is Answer.NONE
    assert choice.warning is not None and "rigid pose" in choice.warning


def test_the_energy_weight_is_the_largest_within_one_paired_standard_error_of_the_best():
    """Breiman's one-standard-error rule on the blocks' paired errors (``one_standard_error``):
    the least held-out RMS at λ = 10⁻³ (session 34's tool1-g kind: neighbours within the
    blocks' noise) gives way to the largest λ whose excess over it lies within one standard
    error of that excess; an excess the same in every block (a standard error of ~0) is
    real, however small, and is not taken, although the blocks' own spread would hide it."""
    from navapp.registration.forces import one_standard_error

    counts = np.array([100, 120, 80, 100, 100])
    base = np.array([1.0, 5.0, 2.5, 0.6, 1.5])  # blocks of unequal difficulty
    noisy = {1e-3: base, 1e-2: base + [0.3, -0.2, 0.1, 0.0, 0.1], 1e-1: base + [0.4, -0.3, 0.3, -0.1, 0.0],
             1.0: base + [0.6, 0.5, 0.4, 0.7, 0.6]}
    # by hand: λ = 0.1's excess, its paired standard error (weights p = counts / 500)
    p = counts / counts.sum()
    d = noisy[1e-1] - base
    se = np.sqrt(5 / 4 * np.sum(p ** 2 * (d - p @ d) ** 2))
    assert 0 < p @ d <= se
    assert one_standard_error(noisy, counts) == 1e-1
    steady = {1e-3: base, 1e-2: base + 0.02}  # 0.02 mm worse in every block
    assert one_standard_error(steady, counts) == 1e-3
    assert one_standard_error({1e-3: base}, counts) == 1e-3


def test_surface_forces_on_a_free_floating_model_is_one_clear_error(small_model):
    from navapp.errors import InputError
    from navapp.registration.pipeline import register

    with pytest.raises(InputError, match="declared supports"):
        register(small_model, {"anterior": small_model.basis.nodes[small_model.basis.surface[:50]]},
                 surface_forces=True)


def test_register_with_surface_forces_shows_the_chosen_answer(held_basis, phantoms, coarse_mesh):
    """``register(surface_forces=True)`` on a posterior-held model, a dent under the scanned
    anterior surface in the preoperative frame, the pose declared: the choice is made, its
    held-out RMS of the shown answer is the least of the three, and ``transform`` moves the
    organ as that answer does (the forces' nodal field where they are shown); a warm
    re-registration shows the basis's answer with a line that says so."""
    from navapp.fitwarning import WarningKind
    from navapp.mechanics.fem import Material
    from navapp.registration.forces import Answer, one_standard_error
    from navapp.registration.model import build_model
    from navapp.registration.pipeline import register
    from navapp.registration.prior import PosePrior
    from navapp.registration.rigid import beta_pose
    from navapp.simulation.truth import Loading, Supports, Tool, ToolLoad, solve_linear

    model = build_model(held_basis, phantoms[0], fiducials=held_basis.nodes[:6])
    s = held_basis.nodes[held_basis.surface]
    top = s[np.argmax(s[:, 1])]
    tool = Tool(tuple(top), (0.0, -1.0, 0.0), 25.0, 15.0, ToolLoad.DISPLACEMENT)
    u_true = solve_linear(coarse_mesh, Loading(gravity=0.0, supports=Supports.POSTERIOR, tool=tool),
                          Material()).reshape(-1, 3)
    scan = held_basis.surface[s[:, 1] > np.percentile(s[:, 1], 60)]
    pts = held_basis.nodes[scan] + u_true[scan] + np.random.default_rng(6).normal(scale=0.3, size=(len(scan), 3))
    reg = register(model, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0), surface_forces=True)
    fc = reg.forces
    assert fc is not None and fc.u is not None
    assert fc.energy_weight == one_standard_error(fc.forces_blocks_mm, fc.block_points)
    scores = {Answer.NONE: fc.none_mm, Answer.BASIS: fc.basis_mm, Answer.FORCES: fc.forces_mm[fc.energy_weight]}
    assert scores[fc.answer] == min(v for v in scores.values() if v is not None)
    assert reg.deformed == (fc.answer is not Answer.NONE)
    x = held_basis.nodes[scan]
    # the pose declared: the forces carry their own rigid part of eq. 8, fitted with them, and
    # the given pose where the posterior does not tell the fitted one from it (data in the given frame)
    assert fc.pose is not None and fc.pose_evidence is not None and fc.pose_evidence.kept_given
    assert np.array_equal(fc.pose, reg.pose_prior.centre)
    by_forces = reg.rigid.apply(beta_pose(fc.pose, model.centroid).apply(x + fc.u[scan]))
    for shown in Answer:  # each answer as ``transform`` shows it
        fc.answer = shown
        expected = {Answer.NONE: reg.rigid.apply(x), Answer.FORCES: by_forces,
                    Answer.BASIS: reg.transform(x, beta=reg.libr.beta)}[shown]
        assert np.allclose(reg.transform(x), expected, atol=1e-6)
    assert not np.allclose(by_forces, reg.transform(x, beta=reg.libr.beta), atol=0.1)
    # a warm re-registration (a live update) does not refit the forces: it shows the basis's
    # answer and says so, once; the fresh one has no such line
    warm = register(model, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0), surface_forces=True,
                    rigid=reg.rigid, beta0=reg.libr.beta)
    said = [w for w in warm.warnings if w.kind is WarningKind.SURFACE_FORCES]
    assert warm.forces is None and len(said) == 1 and "the basis's answer is shown" in said[0].text
    assert np.allclose(warm.transform(x), warm.transform(x, beta=warm.libr.beta))
    assert not any("warm re-registration" in w.text for w in reg.warnings)


def _supports_case(coarse_mesh, supports: str, gravity: float, seed: int = 0):
    """A pressure tool (15 mm deep, 25 mm radius) on the anterior surface of an organ held at
    ``supports``, 30 mm from them at least, with ``gravity`` (m/s²) toward the posterior; the
    anterior 40 % of the surface seen with 0.3 mm noise. Returns the true displacement (M, 3)
    and the points."""
    from scipy.spatial import cKDTree

    from navapp.mechanics.fem import Material
    from navapp.mechanics.supports import held_nodes
    from navapp.simulation.truth import Loading, Supports, Tool, ToolLoad, solve_linear

    rng = np.random.default_rng(seed)
    surface = np.unique(coarse_mesh.boundary_faces())
    s = coarse_mesh.nodes[surface]
    away = cKDTree(coarse_mesh.nodes[held_nodes(coarse_mesh, supports)]).query(s)[0] > 30
    centre = s[rng.choice(np.flatnonzero((s[:, 1] > np.percentile(s[:, 1], 75)) & away))]
    tool = Tool(tuple(centre), (0.0, -1.0, 0.0), 25.0, 15.0, ToolLoad.PRESSURE)
    u = solve_linear(coarse_mesh, Loading(gravity=gravity, supports=Supports(supports), tool=tool),
                     Material()).reshape(-1, 3)
    scan = surface[s[:, 1] > np.percentile(s[:, 1], 60)]
    return u, coarse_mesh.nodes[scan] + u[scan] + rng.normal(scale=0.3, size=(len(scan), 3))


@pytest.mark.parametrize("truth, declared, contradicted", [("ligaments", "posterior", True),
                                                          ("posterior", "posterior", False)])
def test_declared_supports_the_data_contradict_are_warned(coarse_mesh, held_basis, small_basis, phantoms,
                                                          truth, declared, contradicted):
    """The issue's wrong supports: an organ held at its ligaments sagging under gravity (19 mm
    mean) with a tool on it, registered with a posterior support declared. Its answer is worse
    than the undeclared one (the free-floating basis, the same declared pose: measured 11.9
    against 8.5 mm mean over the nodes), and the free basis's fits predict the held-out blocks
    better (4.4 against 7.5 mm), so the answer says the supports are not borne out. Declared as
    the scene held it (posterior, a tool, no gravity: 0.48 against 1.71 mm), no such line."""
    from navapp.registration.model import build_model
    from navapp.registration.pipeline import free_model, register
    from navapp.registration.prior import PosePrior

    assert declared == "posterior"  # the held_basis fixture's
    fid = held_basis.nodes[:6]
    held = build_model(held_basis, phantoms[0], fiducials=fid)
    free = build_model(small_basis, phantoms[0], fiducials=fid)
    u, pts = _supports_case(coarse_mesh, truth, 9.81 if contradicted else 0.0)
    undeclared = register(free, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0))
    reg = register(held, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0), surface_forces=True, undeclared=free)
    x0, x1 = held_basis.nodes, held_basis.nodes + u

    def err(r):
        return float(np.linalg.norm(r.transform(x0) - x1, axis=1).mean())

    fc = reg.forces
    assert fc is not None and fc.free_mm is not None
    said = [w for w in reg.warnings if "declared supports are not borne out" in w.text]
    if contradicted:
        assert err(reg) > err(undeclared)  # the premise: the wrong supports made the answer worse
        assert fc.free_mm < fc.shown_mm and len(said) == 1 and reg.held is None
    else:  # not contradicted; whether the answer rests on the supports is the held check's line
        # (``test_a_force_answer_only_the_declared_supports_make_is_said``; here it does: 0.90 against
        # 1.02 mm held out, within one paired standard error)
        assert err(reg) < err(undeclared) and fc.free_mm > fc.shown_mm and not said and reg.held is not None
    assert fc.as_dict()["supports_contradicted"] is contradicted
    # the default free model is the same mesh's free basis from the cache
    assert np.allclose(free_model(held).basis.Ju, small_basis.Ju, rtol=0, atol=1e-12)


@pytest.mark.parametrize("truth, contradicted", [("ligaments", True), ("posterior", False)])
def test_declared_supports_the_data_contradict_give_the_free_answer(coarse_mesh, held_basis, small_basis, phantoms,
                                                                    truth, contradicted):
    """The basis held at declared supports, without surface forces: where the free-floating
    basis's fits predict the same held-out blocks better, the supports are contradicted and the
    answer is the free-floating model's registration (bit for bit the undeclared one), with the
    line that says why; declared as the scene held the organ, the held answer stays."""
    from navapp.registration.model import build_model
    from navapp.registration.pipeline import register
    from navapp.registration.prior import PosePrior

    fid = held_basis.nodes[:6]
    held = build_model(held_basis, phantoms[0], fiducials=fid)
    free = build_model(small_basis, phantoms[0], fiducials=fid)
    u, pts = _supports_case(coarse_mesh, truth, 9.81 if contradicted else 0.0)
    undeclared = register(free, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0))
    reg = register(held, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0), undeclared=free)
    x0, x1 = held_basis.nodes, held_basis.nodes + u

    def err(r):
        return float(np.linalg.norm(r.transform(x0) - x1, axis=1).mean())

    check = reg.held
    said = [w for w in reg.warnings if "declared supports are not borne out" in w.text]
    assert check is not None and check.held == "posterior" and check.replaced is contradicted
    if contradicted:  # the held answer (measured 19.5 mm mean over the nodes) against the free one's 8.5
        assert check.contradicted and check.free_mm < check.held_mm
        assert reg.model is free and len(said) == 1 and "free-floating model's answer is shown" in said[0].text
        assert err(reg) == err(undeclared)
    else:  # the free basis's fits predict the blocks better (1.02 against 1.37 mm), but neither answer
        # deforms: two rigid answers the supports do not shape, the held one stays, unwarned
        assert reg.model is held and not reg.deformed and not said and err(reg) <= err(undeclared) + 1e-9


@pytest.mark.parametrize("truth, declared, seed, says", [
    ("posterior", "bare_area", 0, "without them the data earn none"),
    ("posterior", "bare_area", 1, "do not tell them from a free-floating organ"),
    ("ligaments", "ligaments", 1, "the held-out data bear out")])
def test_a_deformation_only_the_declared_supports_make_is_said(coarse_mesh, small_basis, phantoms, truth, declared,
                                                             seed, says):
    """Issue 47's wrong supports, where the data cannot contradict them: the held answer deforms
    and either the free-floating basis's fits earn no deformation by the undeclared registration's
    rule (an organ on a posterior bed under a tool, the bare area declared, seed 0: the undeclared
    answer stays rigid), or the held answer predicts the held-out blocks better than they do by
    no more than one paired standard error (seed 1: 0.024 ± 0.041 mm). The deformation shown
    then rests on the declaration alone, and a line says so (on the local-load cases such answers
    were up to 0.7 mm worse than the undeclared one, unwarned: docs/decisions/local-loads.md, "Wrong
    supports, session 38"). The ligaments declared where the scene held them, the gain 0.19 ± 0.06 mm: the data
    tell the answers apart on the held-out blocks, but the supports move the organ 1.34 mm RMS from
    the free-floating answer, more than the 0.52 mm those blocks bear out, √(0.81² − 0.63²): the
    rest lies where no data test it, and a line says so (``HeldCheck.beyond_data``;
    docs/decisions/local-loads.md, "Wrong supports: the change the supports make, weighed against
    what the data bear out")."""
    from navapp.mechanics.basis import BasisSettings, compute_basis
    from navapp.registration.model import build_model
    from navapp.registration.pipeline import register
    from navapp.registration.prior import PosePrior

    basis = compute_basis(coarse_mesh, BasisSettings(k=12, supports=declared))
    fid = basis.nodes[:6]
    held = build_model(basis, phantoms[0], fiducials=fid)
    free = build_model(small_basis, phantoms[0], fiducials=fid)
    _, pts = _supports_case(coarse_mesh, truth, 0.0, seed)
    reg = register(held, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0), undeclared=free)
    check = reg.held
    said = [w for w in reg.warnings if "rests on the declared supports" in w.text]
    assert check is not None and reg.model is held and reg.deformed and not check.contradicted
    assert check.rests_on_supports is (says is not None) and check.as_dict()["rests_on_supports"] is (says is not None)
    assert len(said) == (says is not None) and (says is None or says in said[0].text)
    if says == "without them the data earn none":
        undeclared = register(free, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0))
        assert not check.free_earns and not undeclared.deformed
    else:
        assert check.free_earns
    if says == "the held-out data bear out":
        # the data tell them apart; the change over the organ is measured against the undeclared
        # registration's own answer, over the organ's nodes
        from navapp.registration.uncertainty import organ_nodes

        assert check.gain_mm > check.gain_se_mm and not check.undecided and check.beyond_data
        undeclared = register(free, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0))
        at = basis.nodes[organ_nodes(held)]
        rms = float(np.sqrt(np.mean(np.sum((reg.transform(at) - undeclared.transform(at)) ** 2, axis=1))))
        assert check.organ_change_mm == pytest.approx(rms, rel=1e-9) and rms > check.borne_out_mm
        assert check.borne_out_mm == pytest.approx(np.sqrt(check.free_mm ** 2 - check.held_mm ** 2))


def test_the_change_the_supports_make_is_weighed_against_what_the_held_out_data_bear_out():
    """``HeldCheck.beyond_data``: the held answer's change over the organ (RMS, from the
    free-floating answer) against √(free² − held²) of the held-out RMS — what the held answer
    removes from the free basis's held-out misfit. No margin: equal is borne out; not measured
    (NaN) says nothing; a contradicted or replaced check is not this line's."""
    from navapp.registration.support import HeldCheck

    base = HeldCheck("posterior", held_mm=0.6, free_mm=1.0, held_deforms=True, gain_mm=0.4, gain_se_mm=0.1)
    assert base.borne_out_mm == pytest.approx(0.8) and not base.undecided
    assert not base.beyond_data and not base.rests_on_supports and base.warning is None  # not measured
    within = replace(base, organ_change_mm=0.8)
    assert not within.beyond_data and within.warning is None
    beyond = replace(base, organ_change_mm=0.81)
    assert beyond.beyond_data and beyond.rests_on_supports
    assert beyond.warning == ("the deformation shown rests on the declared supports (posterior): they move the organ "
                              "0.81 mm (RMS) from the free-floating answer, more than the 0.80 mm the held-out data "
                              "bear out (held out 0.60 mm held against 1.00 mm free) — check where the organ is held")
    assert beyond.as_dict()["beyond_data"] is True and beyond.as_dict()["organ_change_mm"] == 0.81
    assert not replace(beyond, held_deforms=False).rests_on_supports  # a rigid answer: the supports shape nothing
    contradicted = replace(beyond, held_mm=1.1)  # the free basis predicts better: the other line
    assert contradicted.borne_out_mm == 0.0 and not contradicted.rests_on_supports



def test_a_pose_the_posterior_does_not_tell_from_the_given_one_is_the_given_one(forces, held_basis, coarse_mesh):
    """A 15 mm dent seen in the given frame (pre-aligned, declared to 1.5 mm / 1.5°) and forces
    held stiff (λ = 10): fitted with them, the pose takes up the part of the dent they leave
    and moves the whole organ, 0.86 mm over the organ against its posterior σ of 1.5 mm
    (measured) — node error 0.74 mm, worse than no correction's 0.60 (tooldraw3_1-c's fault).
    Not told apart from the given pose, the forces are fitted at the given pose (measured 0.47
    mm). A 4.1 mm / 2.9° tracker offset declared at 5 mm / 5° is told apart (5.3 mm moved
    against σ 1.8 at λ = 1) and its fitted pose kept (0.67 mm against 5.5)."""
    from navapp.registration.forces import PoseTerm, choose_deformation
    from navapp.registration.prior import PosePrior

    u_true, pts = _dent(held_basis, coarse_mesh, 25.0, 15.0, noise=0.3)
    centroid = held_basis.nodes.mean(0)

    def error(moved, truth):
        return float(np.linalg.norm(moved - truth, axis=1).mean())

    term = PoseTerm.of(PosePrior(1.5, 1.5, feature_sd_mm=0.3), centroid)
    truth = held_basis.nodes + u_true
    choice = choose_deformation(forces, None, {"anterior": pts}, None, None, weights=(10.0,), pose=term)
    pf = forces.responses(pts)
    wf = forces.fit_weights(pf, 10.0, pose=term)
    fitted = _offset(held_basis.nodes + forces.field(pf, wf), wf.q, centroid)
    shown = _offset(held_basis.nodes + choice.u, choice.pose, centroid)
    none = error(held_basis.nodes, truth)
    assert error(fitted, truth) > none  # the sliding pose: worse than no correction
    assert error(shown, truth) < none
    ev = choice.pose_evidence
    assert ev is not None and ev.kept_given and 0 < ev.moved_mm < ev.sigma_mm
    assert choice.pose is not None and np.array_equal(choice.pose, term.centre)

    q_true = np.array([2.0, -3.0, 2.0, np.radians(2.0), np.radians(-1.5), np.radians(1.5)])
    truth = _offset(held_basis.nodes + u_true, q_true, centroid)
    term = PoseTerm.of(PosePrior(5.0, 5.0, feature_sd_mm=0.3), centroid)
    choice = choose_deformation(forces, None, {"anterior": _offset(pts, q_true, centroid)}, None, None,
                                weights=(1.0,), pose=term)
    assert choice.pose_evidence is not None and not choice.pose_evidence.kept_given
    assert error(_offset(held_basis.nodes + choice.u, choice.pose, centroid), truth) < 1.0


def test_the_answer_at_the_given_pose_is_the_lower_phi_of_two_starts(forces, held_basis, coarse_mesh):
    """A 40 mm dent of 20 mm radius seen in the given frame (declared to 1.5 mm / 1.5°), λ =
    10⁻³: the forces' fit at the given pose from w = 0 ends at Φ 0.85 mm², where the same
    objective started from the forces fitted with the pose reaches 0.66 (measured; on tool2-d at
    S + all, 1.78 against 0.64, TRE 3.87 against 2.18 mm). The pose is not told from the given
    one, so the answer is fitted there from both starts and the lower Φ is shown. The test is of
    the fit, not of the truth: here, at λ = 10⁻³ on 0.3 mm noise, the lower Φ is the farther from
    the true displacement (node error 1.61 against 1.09 mm); what it does to the TRE is measured
    on the local-load cases (docs/decisions/local-loads.md, "the given pose from two starts")."""
    from navapp.registration.forces import PoseTerm, choose_deformation
    from navapp.registration.prior import PosePrior

    _, pts = _dent(held_basis, coarse_mesh, 20.0, 40.0, noise=0.3)
    term = PoseTerm.of(PosePrior(1.5, 1.5, feature_sd_mm=0.3), held_basis.nodes.mean(0))
    choice = choose_deformation(forces, None, {"anterior": pts}, None, None, weights=(1e-3,), pose=term)
    assert choice.pose_evidence is not None and choice.pose_evidence.kept_given
    pf = forces.responses(pts)
    from_zero = forces.fit_weights(pf, 1e-3, pose=term, held_q=term.centre)
    warm = forces.fit_weights(pf, 1e-3, pose=term, held_q=term.centre, w0=forces.fit_weights(pf, 1e-3, pose=term).w)
    assert warm.phi < 0.9 * from_zero.phi  # the fit from w = 0 stops short
    assert choice.fit is not None and choice.fit.phi == pytest.approx(warm.phi, rel=1e-12)
    assert choice.fit.phi0 == pytest.approx(from_zero.phi0, rel=1e-12)  # Φ at f = 0, whichever start won
    assert np.allclose(choice.u, forces.field(pf, warm), rtol=0, atol=1e-9)


@pytest.mark.parametrize("truth, declared, says", [
    ("ligaments", "posterior", "without them the data earn none"),
    ("bare_area", "posterior", "do not tell them from a free-floating organ"),
    ("posterior", "ligaments", None)])
def test_a_force_answer_only_the_declared_supports_make_is_said(coarse_mesh, small_basis, phantoms, truth, declared,
                                                              says):
    """The surface forces' answer held at declared supports is judged as the held basis's answer
    is (``HeldCheck`` on the choice's own folds, ``ForceChoice.held_check``): the posterior
    declared on an organ held at its ligaments under a tool (no gravity), the forces shown (node
    error measured 1.06 mm, undeclared 2.00): the free-floating basis's fits earn no deformation
    over no deformation on the same blocks (1.40 against 1.40 mm), so the deformation rests on the
    declaration and a line says so. The posterior declared on one held at its bare area: the free
    fits earn one (0.98 against 2.35 mm) but the forces' gain over them, 0.04 mm, is within its
    paired standard error (0.51). Without the check neither had a line: on the local-load cases
    such answers were up to 2.8 mm worse than the undeclared one, unwarned
    (docs/decisions/local-loads.md, "Wrong supports with the surface forces"). The ligaments
    declared on a posterior-held organ: the free basis predicts the blocks better, its own line,
    and no second check."""
    from navapp.mechanics.basis import BasisSettings, compute_basis
    from navapp.registration.model import build_model
    from navapp.registration.pipeline import register
    from navapp.registration.prior import PosePrior

    basis = compute_basis(coarse_mesh, BasisSettings(k=12, supports=declared))
    fid = basis.nodes[:6]
    held = build_model(basis, phantoms[0], fiducials=fid)
    free = build_model(small_basis, phantoms[0], fiducials=fid)
    _, pts = _supports_case(coarse_mesh, truth, 0.0)
    reg = register(held, {"anterior": pts}, pose_prior=PosePrior(2.0, 2.0), surface_forces=True, undeclared=free)
    said = [w for w in reg.warnings if "rests on the declared supports" in w.text]
    fc, check = reg.forces, reg.held
    assert fc is not None and reg.model is held
    if says is None:
        assert fc.supports_contradicted and check is None and not said
        assert [w for w in reg.warnings if "not borne out" in w.text]
        return
    assert check is not None and reg.deformed and not check.contradicted and check.held == declared
    assert check.held_mm == fc.shown_mm and check.free_mm == fc.free_mm and check.free_rigid_mm == fc.none_mm
    assert check.rests_on_supports and len(said) == 1 and says in said[0].text
    if says == "without them the data earn none":
        assert not check.free_earns
    else:
        assert check.free_earns and check.undecided


def test_the_pose_fit_starts_where_it_is_told(forces, held_basis, coarse_mesh):
    """``fit_weights(q0=)``: the joint fit of the forces and the rigid part starts at q0, so Φ at
    the start (``WeightFit.phi0``, w = 0) is the misfit of the undeformed organ posed at q0 plus
    the prior's term there, and no iteration leaves q at q0 (the probe of session 43: a start at
    another pose, the undeclared answer's or the truth's, reaches the same Φ on the study's
    offset cases; docs/decisions/local-loads.md, "the objective prefers the wrong pose")."""
    from navapp.registration.forces import ForceOptions, PoseTerm
    from navapp.registration.prior import PosePrior

    _, pts = _dent(held_basis, coarse_mesh, 25.0, 15.0, noise=0.3)
    term = PoseTerm.of(PosePrior(5.0, 5.0, feature_sd_mm=0.3), held_basis.nodes.mean(0))
    pf = forces.responses(pts)
    q0 = np.array([1.5, -2.0, 1.0, 0.02, -0.01, 0.015])
    still = forces.fit_weights(pf, 1.0, options=ForceOptions(energy_weight=1.0, iterations=0), pose=term, q0=q0)
    assert np.array_equal(still.q, q0)
    d = forces.distances(term.to_model(pts, q0)[0], np.zeros(3 * len(forces.all_surface)))[0]
    assert still.phi0 == pytest.approx(float(d @ d) / len(d) + term.value(q0), rel=1e-12)
    moved = forces.fit_weights(pf, 1.0, pose=term, q0=q0)
    assert moved.phi < still.phi0 and not np.array_equal(moved.q, q0)
