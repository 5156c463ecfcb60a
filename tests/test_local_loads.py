"""Local loads: the tool indentation truth, the kept pose and its sliding directions, and
the cross-validated warning when the data cannot determine the answer."""

import numpy as np
import pytest
import trimesh

from navapp.errors import InputError, NavappError
from navapp.fitwarning import WarningKind
from navapp.mechanics.fem import Material
from navapp.simulation.scene import parse_scene
from navapp.simulation.truth import (
    Loading,
    Supports,
    Tool,
    ToolLoad,
    solve_linear,
    solve_neo_hookean,
    supported_nodes,
    tool_patch,
)


@pytest.fixture(scope="module")
def block():
    """A 60 × 30 × 40 mm block of P1 tets (scikit-fem's generator, not navapp's mesher)."""
    from skfem import MeshTet

    from navapp.anatomy.meshing import TetMesh

    m = MeshTet.init_tensor(np.linspace(0, 60, 13), np.linspace(0, 30, 7), np.linspace(0, 40, 9))
    nodes, tets = np.asarray(m.p.T, float), np.asarray(m.t.T, int)
    e = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    flip = np.linalg.det(e) < 0  # navapp's meshes are positively oriented
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    return TetMesh(nodes, tets)


def _press(mesh, depth=6.0, load=ToolLoad.DISPLACEMENT):
    # a tip on the top (anterior, +y) face pushing down; the bottom face rests on a bed
    return Loading(gravity=0.0, supports=Supports.POSTERIOR,
                   tool=Tool((30.0, 30.0, 20.0), (0.0, -1.0, 0.0), 12.0, depth, load))


def test_tool_displacement_truth_equals_scikit_fem(block):
    """The prescribed indentation solved by navapp equals scikit-fem's own solve of the
    same boundary-value problem (its assembly, its condensation, its solver)."""
    from skfem import Basis, ElementTetP1, ElementVector, MeshTet, asm, condense, solve
    from skfem.models.elasticity import linear_elasticity

    mat = Material(E=5000.0, nu=0.45)
    loading = _press(block)
    u = solve_linear(block, loading, mat)
    m = MeshTet(block.nodes.T, block.tets.T)
    ib = Basis(m, ElementVector(ElementTetP1()), intorder=1)
    K = asm(linear_elasticity(*mat.lame()), ib)
    # the same boundary condition: the bed (posterior-facing nodes) held, the patch prescribed
    bottom = supported_nodes(block, supports=Supports.POSTERIOR)["posterior_bed"]
    assert np.all(block.nodes[bottom, 1] < 1e-9) and len(bottom) > 100
    nodes, w = tool_patch(block, loading.tool)
    x = np.zeros(K.shape[0])
    # skfem's vector P1 DOFs are node-major like navapp's (3 i + axis)
    for n, wi in zip(nodes, w, strict=True):
        x[3 * n + 1] = -6.0 * wi
    held = np.concatenate([(3 * bottom[:, None] + np.arange(3)).ravel(), (3 * nodes[:, None] + np.arange(3)).ravel()])
    ref = solve(*condense(K, np.zeros(K.shape[0]), x=x, D=held))
    assert np.abs(u.ravel() - ref).max() < 1e-8 * 6.0
    centre = nodes[np.argmin(np.linalg.norm(block.nodes[nodes] - [30.0, 30.0, 20.0], axis=1))]
    assert u[centre, 1] == pytest.approx(-6.0)
    assert np.abs(u[bottom]).max() == 0.0


def test_tool_pressure_reaches_its_depth_and_neo_hookean_agrees_at_small_load(block):
    mat = Material(E=5000.0, nu=0.45)
    lin = solve_linear(block, _press(block, 0.5, ToolLoad.PRESSURE), mat)
    nodes, _ = tool_patch(block, _press(block).tool)
    centre = nodes[np.argmin(np.linalg.norm(block.nodes[nodes] - [30.0, 30.0, 20.0], axis=1))]
    assert lin[centre, 1] == pytest.approx(-0.5, rel=1e-6)
    # pressure, not a prescribed dent: the patch's rim is free and moves less than the centre
    assert np.abs(lin[nodes, 1]).min() < 0.5 * np.abs(lin[centre, 1])
    nh = solve_neo_hookean(block, _press(block, 0.5, ToolLoad.PRESSURE), mat)
    assert np.abs(nh - lin).max() < 0.03 * 0.5  # 1 % strain: geometric nonlinearity is small
    with pytest.raises(NavappError, match="linear truth"):
        solve_neo_hookean(block, _press(block), mat)


def test_neo_hookean_truth_reaches_the_declared_depth(block):
    """The dead load scaled to the linear depth is not the depth the neo-Hookean truth
    reaches (here 10 % short; on phantom 1 a lobe went 116 mm for a declared 45): the truth
    scales its tool load until its own patch centre is at the declared depth."""
    from navapp.simulation.truth import _free_dofs, solve_hyperelastic, tool_force

    mat = Material(E=5000.0, nu=0.45)
    load = _press(block, 10.0, ToolLoad.PRESSURE)
    nodes, _ = tool_patch(block, load.tool)
    centre = nodes[np.argmin(np.linalg.norm(block.nodes[nodes] - [30.0, 30.0, 20.0], axis=1))]
    seen = []
    nh = solve_neo_hookean(block, load, mat, reached=seen.append)
    assert -nh[centre, 1] == pytest.approx(10.0, rel=0.01)
    assert seen[-1] == 1.0 and all(b > a for a, b in zip(seen, seen[1:], strict=False))
    # the search toward the depth moves the bar too (it stood at the last increment's figure)
    assert sum(0.95 < s < 1.0 for s in seen) >= 1
    at_linear_load = solve_hyperelastic(block.nodes, block.tets, tool_force(block, load, mat),
                                        _free_dofs(block, load), mat)
    assert abs(-at_linear_load[centre, 1] - 10.0) > 0.05 * 10.0


def test_with_gravity_the_tool_adds_its_depth_as_in_the_linear_truth(block):
    """The depth is the tool's own push, beyond where the body loads left the patch: as the
    linear truth's superposition has it (the total would stop the tool short by the sag)."""
    mat = Material(E=5000.0, nu=0.45)
    sag = Loading(gravity=9.81, supports=Supports.POSTERIOR)
    load = Loading(gravity=9.81, supports=Supports.POSTERIOR, tool=_press(block, 4.0, ToolLoad.PRESSURE).tool)
    nodes, _ = tool_patch(block, load.tool)
    centre = nodes[np.argmin(np.linalg.norm(block.nodes[nodes] - [30.0, 30.0, 20.0], axis=1))]
    lin = solve_linear(block, load, mat) - solve_linear(block, sag, mat)
    assert -lin[centre, 1] == pytest.approx(4.0, rel=1e-6)
    below = solve_neo_hookean(block, sag, mat)
    assert -below[centre, 1] > 0.5  # the sag is not negligible beside 1 % of 4 mm
    nh = solve_neo_hookean(block, load, mat) - below
    assert -nh[centre, 1] == pytest.approx(4.0, rel=0.01)


def test_tool_scene_keys_are_checked():
    base = {"anatomy": {"phantom": 0}, "deformation": {"gravity": False, "supports": "bare_area"},
            "tool": {"site": "anterior", "at": [0.0, 60.0, 0.0], "radius_mm": 15.0, "depth_mm": 30.0}}
    scene = parse_scene(base)
    assert scene.tool.site == "anterior" and scene.tool.at == (0.0, 60.0, 0.0) and not scene.gravity
    bad = [({"tool": {**base["tool"], "site": "posterior"}}, "tool.site"),
           ({"tool": {**base["tool"], "depth_mm": 200.0}}, "tool.depth_mm"),
           ({"tool": {**base["tool"], "at": [1.0, 2.0]}}, "tool.at"),
           ({"tool": {**base["tool"], "tip": 3}}, "unknown key tool.tip"),
           ({"deformation": {"supports": "table"}}, "deformation.supports"),
           ({"deformation": {"large": True}}, "needs the linear truth"),
           ({"deformation": {"gravity_tilt_deg": 720.0}}, "gravity_tilt_deg"),
           ({"stylus": {"pattern": "patch"}}, "needs stylus.at")]
    for change, message in bad:
        data = {**base, **change}
        if "deformation" in change and "large" in change["deformation"]:
            data["deformation"] = {**base["deformation"], **change["deformation"]}
        with pytest.raises(InputError, match=message):
            parse_scene(data)


@pytest.fixture(scope="module")
def sphere_model(cache_root):
    """A ball of radius 60 mm, meshed and given a small basis: the most regular surface."""
    from navapp.anatomy.meshing import cached_tetmesh
    from navapp.anatomy.model import PreopModel
    from navapp.mechanics.basis import BasisSettings, load_or_compute_basis
    from navapp.registration.model import build_model

    ball = trimesh.creation.icosphere(subdivisions=4, radius=60.0)
    mesh, _ = cached_tetmesh(ball, 10.0, cache_root)
    basis, _ = load_or_compute_basis(mesh, BasisSettings(k=12), cache_root=cache_root)
    return build_model(basis, PreopModel(liver=ball))


def _dented_cap(model, depth=12.0, radius=20.0):
    """Points on the upper cap of the ball, already in the model's frame, pressed in near
    one side of the cap by a smooth dent (no rigid motion at all)."""
    rest = model.features["liver"].rest
    cap = rest[rest[:, 2] > 25.0]
    centre = np.array([0.0, 35.0, 48.7])
    centre *= 60.0 / np.linalg.norm(centre)
    r = np.linalg.norm(cap - centre, axis=1)
    inward = -cap / np.linalg.norm(cap, axis=1, keepdims=True)
    return {"anterior": cap + (depth * np.clip(1 - (r / radius) ** 2, 0, None) ** 2)[:, None] * inward}


def test_a_partial_sphere_keeps_its_given_pose_and_names_its_sliding_motions(sphere_model):
    from navapp.registration.pipeline import RobustOptions, register

    data = _dented_cap(sphere_model)
    probe = sphere_model.basis.nodes
    slid = register(sphere_model, data, deform=False, init=RobustOptions.unguarded())
    moved = np.linalg.norm(slid.rigid.apply(probe) - probe, axis=1).mean()
    assert moved > 1.0  # without the rule, ICP slides the ball to share out the dent
    reg = register(sphere_model, data, deform=False)
    assert reg.pose_choice is not None and reg.pose_choice.kept
    assert np.array_equal(reg.rigid.apply(probe), probe)
    # the kept pose reports its own residual (the dent's), not the 0 of a pose nobody fitted
    dent = np.linalg.norm(data["anterior"] - _dented_cap(sphere_model, depth=0.0)["anterior"], axis=1)
    assert 0.3 * np.sqrt(np.mean(dent ** 2)) < reg.rigid.rms_mm <= np.sqrt(np.mean(dent ** 2)) + 0.5
    assert reg.determinacy is not None
    rotations = [r for r, _, _ in reg.determinacy.weak if r is not None]
    assert len(rotations) == 3  # a ball turns freely about its centre
    assert "rotation about" in reg.determinacy.warning
    assert reg.determinacy.warning in [w.text for w in reg.warnings]
    # Slicer hears it too: the status line carries every warning, and no "fit ok"
    from navapp.tracking.results import ascii_text, status_line

    line = status_line(reg)
    assert ascii_text(reg.determinacy.warning) in line and "fit ok" not in line
    assert f"{reg.rigid.rms_mm:.2f} mm" in line


def test_a_distinctive_surface_has_no_sliding_motion_and_moved_data_are_refitted(small_model):
    from navapp.registration.pipeline import register
    from navapp.registration.rotation import rotation

    rest = small_model.features["liver"].rest
    front = rest[rest[:, 1] > np.median(rest[:, 1])]
    R, c = rotation(np.radians([6.0, -4.0, 5.0])), small_model.centroid
    reg = register(small_model, {"anterior": (front - c) @ R.T + c + [4.0, -3.0, 2.0]}, deform=False)
    assert not reg.pose_choice.kept  # the given pose is 8 mm off: ICP's is better by the margin
    assert reg.determinacy.warning is None and reg.determinacy.condition < 1e3
    err = np.linalg.norm(reg.rigid.apply(rest) - ((rest - c) @ R.T + c + [4.0, -3.0, 2.0]), axis=1).max()
    assert err < 0.5


def test_the_warning_fires_where_the_data_cannot_determine_the_answer(small_model):
    """Data already aligned, on the undeformed model but for one local dent: the deformation
    fitted to part of them predicts the rest worse than none, so the answer is the given
    pose itself (no worse than no correction) and one line says why. A deformation that is
    in the basis is supported and kept."""
    from navapp.registration.pipeline import register

    rest = small_model.features["liver"].rest
    front = rest[rest[:, 1] > np.percentile(rest[:, 1], 40)]
    centre = front[np.argmax(front[:, 0])]
    r = np.linalg.norm(front - centre, axis=1)
    dented = front + (15.0 * np.clip(1 - (r / 30.0) ** 2, 0, None) ** 2)[:, None] * [0.0, -1.0, 0.0]
    reg = register(small_model, {"anterior": dented})
    assert reg.support is not None and not reg.support.supported
    assert not reg.deformed
    probe = small_model.basis.nodes
    assert np.array_equal(reg.transform(probe), probe)  # exactly the given pose
    assert any(w.text.startswith("deformation not supported by the data") for w in reg.warnings)

    n = small_model.basis.Ju.shape[1]
    alpha = np.zeros(n)
    alpha[::7] = 1.5
    moved = front + (small_model.features["liver"].B @ (small_model.basis.Ju @ alpha).reshape(-1, 3))[
        rest[:, 1] > np.percentile(rest[:, 1], 40)]
    good = register(small_model, {"anterior": moved})
    assert good.support is not None and good.support.supported and good.deformed
    assert not any(w.text.startswith("deformation not supported") for w in good.warnings)


def test_the_pose_most_of_a_dented_scan_agrees_on_is_taken_not_icps_compromise(small_model):
    """A partial scan most of which moved rigidly (the lobe swung by a few mm) while a deep
    dent pressed the rest in: the trimmed fit from the given pose finds the motion most of
    the points share, ICP fitted to every point shares the dent's misfit out instead."""
    from navapp.registration.pipeline import RobustOptions, register
    from navapp.registration.pose import PoseSource
    from navapp.registration.rotation import rotation

    rest = small_model.features["liver"].rest
    c0 = rest[np.argmax(rest[:, 1])]
    scan = rest[np.linalg.norm(rest - c0, axis=1) < 60.0]
    R, pivot, shift = rotation(np.radians([3.0, -2.0, 2.0])), scan.mean(0), np.array([3.0, -4.0, 2.0])
    swung = (scan - pivot) @ R.T + pivot + shift
    tip = scan[np.argmax(scan[:, 0])]
    r = np.linalg.norm(scan - tip, axis=1)
    dent = (25.0 * np.clip(1 - (r / 35.0) ** 2, 0, None) ** 2)[:, None] * [0.0, -1.0, 0.0]
    data = {"anterior": swung + dent}
    assert 0.15 < np.mean(np.linalg.norm(dent, axis=1) > 1.0) < 0.45  # the dent moves a minority

    def pose_error(reg):
        truth = (rest - pivot) @ R.T + pivot + shift
        return np.linalg.norm(reg.rigid.apply(rest) - truth, axis=1).mean()

    icp = register(small_model, data, deform=False, init=RobustOptions.unguarded())
    reg = register(small_model, data, deform=False)
    assert reg.pose_choice.source is PoseSource.LOCAL and reg.rigid.kept
    assert reg.pose_choice.on_model[PoseSource.LOCAL] > reg.pose_choice.on_model[PoseSource.FITTED]
    assert pose_error(reg) < 0.3 < 2.0 < pose_error(icp)


def test_data_off_the_model_everywhere_do_not_keep_the_given_pose(small_model, phantoms):
    """Data a few mm off the model everywhere, with no rigid component: the surfaces cross
    along lines (as a global sag crosses the model), the trimmed fit stays at the given pose
    on the crossing points, but too few points lie on the model there to call the data
    aligned, so the pose is ICP's and LIBR may move it (phantom2-N had lost 2.5 mm this way)."""
    from scipy.spatial import cKDTree

    from navapp.registration.pipeline import register
    from navapp.registration.pose import POSE_RULE, PoseSource

    liver = phantoms[0].liver
    rest = small_model.features["liver"].rest
    front = rest[rest[:, 1] > np.percentile(rest[:, 1], 40)]
    normals = liver.vertex_normals[cKDTree(liver.vertices).query(front)[1]]
    u = 8.0 * np.sin(2 * np.pi * front[:, 0] / 40.0) * np.sin(2 * np.pi * front[:, 2] / 40.0)
    reg = register(small_model, {"anterior": front + u[:, None] * normals}, deform=False)
    assert reg.pose_choice.moved_mm < 4.0  # the trimmed fit alone would have kept the given pose
    assert reg.pose_choice.on_model[PoseSource.LOCAL] < POSE_RULE.aligned
    assert reg.pose_choice.source is PoseSource.FITTED and not reg.rigid.kept


def _dented_scan(liver, model, depth, radius, far_mm):
    """A 40 mm scan of the front of ``liver`` (its vertices, (V, 3) mm) at its right tip,
    already aligned, pressed in by a smooth dent of ``depth`` mm and footprint ``radius`` mm
    at the scan's centre; and a function giving the mean motion an answer puts on the mesh
    nodes farther than ``far_mm`` from the dent (truly at rest)."""
    front = liver[liver[:, 1] > np.percentile(liver[:, 1], 40)]
    c0 = front[np.argmax(front[:, 0])]
    scan = front[np.linalg.norm(front - c0, axis=1) < 40.0]
    tip = scan.mean(0)
    r = np.linalg.norm(scan - tip, axis=1)
    data = {"anterior": scan + (depth * np.clip(1 - (r / radius) ** 2, 0, None) ** 2)[:, None] * [0.0, -1.0, 0.0]}
    nodes = model.basis.nodes
    far = nodes[np.linalg.norm(nodes - tip, axis=1) > far_mm]

    def far_motion(reg):
        return float(np.linalg.norm(reg.transform(far) - far, axis=1).mean())

    return data, far_motion


def test_a_pose_the_fit_does_not_pay_for_is_not_taken_over_the_given_one(small_model, phantoms, monkeypatch):
    """A partial scan over a deep dent, already aligned, most of it pressed in by several mm:
    no pose puts most of it on the model, so the given pose is not kept as aligned, and the
    multi-start ICP ends tens of millimetres away, where the deformable model fits the dented
    patch about as well as at the given pose. The move is not earned by a better fit: the
    given pose is held (``pose.prefer_given``) and one line says ICP's pose is not earned by the fit.
    Without the rule the organ far from the dent, which did not move, is moved tens of mm."""
    import navapp.registration.pipeline as pipeline
    from navapp.registration.pipeline import RobustOptions
    from navapp.registration.pose import POSE_RULE, PoseSource
    from navapp.registration.support import SupportOptions

    data, far_motion = _dented_scan(phantoms[0].liver.vertices, small_model, 45.0, 35.0, far_mm=80.0)
    nodes = small_model.basis.nodes
    reg = pipeline.register(small_model, data)
    choice = reg.pose_choice
    assert choice.source is PoseSource.GIVEN_FITS and reg.rigid.kept
    assert choice.fits.given_rms_mm <= POSE_RULE.given_ratio * choice.fits.fitted_rms_mm
    assert np.allclose(reg.rigid.apply(nodes), nodes)
    assert any(w.text.startswith("ICP's pose is not earned by the fit: it moved") for w in reg.warnings)
    assert far_motion(reg) < 2.0

    monkeypatch.setattr(pipeline, "prefer_given", lambda *a, **k: None)
    before = pipeline.register(small_model, data)
    assert before.pose_choice.source is PoseSource.FITTED
    assert far_motion(before) > 15.0
    # where ICP's pose stays the answer (as if the fit had earned its move), no line says its pose
    # is in doubt (it said "neither pose is determined" right after a rule that had just decided);
    # the comparison is recorded
    assert not any(w.text.startswith("ICP's pose") for w in before.warnings)
    assert before.pose_choice.as_dict()["fitted_shift_mm"] > 5.0
    # this slide's correction is within its own uncertainty (z < 1), so the cross-validation's
    # "do not rely on it" is not let go (``Support.outweighs``)
    s = before.support
    assert s.correction_mm is not None and s.correction_mm < s.z_strong * s.sigma_mm and not s.outweighs
    assert any(w.text.startswith("deformation not supported by the data") for w in before.warnings)

    # were the correction to outweigh its σ, the same answer would be shown without that line
    strong = pipeline.register(small_model, data, init=RobustOptions(support=SupportOptions(z_strong=0.0)))
    assert strong.support.outweighs and strong.deformed
    assert np.array_equal(strong.transform(nodes), before.transform(nodes))  # the answer is not changed
    assert not any(w.text.startswith("deformation not supported") for w in strong.warnings)


def _lifted_lobe(liver, tip_deg, base_deg):
    """A scan of the front of the right lobe of ``liver`` (its vertices, (V, 3) mm) alone, the lobe
    lifted about a vertical hinge at its base: the base turned ``base_deg``, the tip ``tip_deg``
    (a bend when they differ), the rest of the organ where it was; and the mesh-free check of an
    answer: the mean motion it puts on the vertices left of the hinge by 20 mm and more."""
    from scipy.spatial.transform import Rotation

    front = liver[liver[:, 1] > np.percentile(liver[:, 1], 40)]
    x0 = np.percentile(liver[:, 0], 65)
    lobe = front[front[:, 0] > x0]
    hinge = np.array([x0, lobe[:, 1].mean(), lobe[:, 2].mean()])
    along = (lobe[:, 0] - x0) / (lobe[:, 0].max() - x0)
    turn = np.radians(base_deg + (tip_deg - base_deg) * along)
    R = Rotation.from_rotvec(turn[:, None] * np.array([0.0, 0.0, 1.0])).as_matrix()
    rest = liver[liver[:, 0] < x0 - 20.0]

    def rest_motion(reg):
        return float(np.linalg.norm(reg.transform(rest) - rest, axis=1).mean())

    return {"anterior": np.einsum("nij,nj->ni", R, lobe - hinge) + hinge}, rest_motion


def test_a_turn_no_tracker_makes_is_not_taken_when_the_answer_from_it_is_in_doubt(small_model, phantoms, monkeypatch):
    """A scan of a lifted right lobe alone (tip turned 80°, base 40°), already aligned. The
    undeformed organ fits it best turned about 76° from the given pose, where the pose alone
    leaves most of the scan off the model and the deformable fit stays poor: the answer from
    there is in doubt, and the given pose fits worse by more than the margin. No tracker's
    registration is 76° off: the given pose is held (``PoseSource.GIVEN_TURN``) and one line
    says so, and the rest of the organ, which did not move, stays. Without the rule (a limit
    of 180°) the rest of the organ is turned with the lobe, tens of mm.

    A whole-front scan turned 70°, as a tracker that far off would give, puts every point on
    the model at ICP's pose: that turn is taken, and said. A lobe lifted less steeply (60° /
    30°) is explained by the deformation from a pose turned 57° (a good fit, the deformation
    supported: the answer was not in doubt, and it was silent); the pose alone leaves most of
    the scan off the model, so the turn is not confirmed and the given pose is held too (the
    held-out tooltest1-d: 77 mm at ICP's 67° against 18.6 with no correction)."""
    from dataclasses import replace

    import navapp.registration.pipeline as pipeline
    from navapp.registration.pose import POSE_RULE, PoseSource, prefer_given

    liver = phantoms[0].liver.vertices
    data, rest_motion = _lifted_lobe(liver, 80.0, 40.0)
    reg = pipeline.register(small_model, data)
    choice = reg.pose_choice
    assert choice.source is PoseSource.GIVEN_TURN and reg.rigid.kept, choice.as_dict()
    assert choice.turn_deg > POSE_RULE.tracker_turn_deg
    assert choice.fits.given_rms_mm > POSE_RULE.given_ratio * choice.fits.fitted_rms_mm  # not the other rule
    assert choice.on_model[PoseSource.FITTED] < POSE_RULE.consensus
    line = next(w.text for w in reg.warnings if w.text.startswith("ICP's pose is not taken: it moved the organ"))
    assert f"turned it {choice.turn_deg:.0f}°" in line and "further than a tracker's registration errs" in line
    assert choice.as_dict()["source"] == "given-turn" and choice.as_dict()["fitted_turn_deg"] > 45.0

    monkeypatch.setattr(pipeline, "prefer_given",
                        lambda c, f: prefer_given(c, f, replace(POSE_RULE, tracker_turn_deg=180.0)))
    before = pipeline.register(small_model, data)
    assert before.pose_choice.source is PoseSource.FITTED
    print(f"the rest of the organ moved {rest_motion(reg):.1f} mm (given pose held), {rest_motion(before):.1f} (ICP's)")
    # held, the k = 12 deformation still drags the rest of the organ after the lifted lobe
    assert rest_motion(before) > 40.0 and rest_motion(reg) < 0.5 * rest_motion(before)
    monkeypatch.undo()

    front = liver[liver[:, 1] > np.percentile(liver[:, 1], 40)]
    c = front.mean(0)
    axis = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.radians(70.0) * axis).as_matrix()
    offset = pipeline.register(small_model, {"anterior": (front - c) @ R.T + c})
    assert offset.pose_choice.source is PoseSource.FITTED
    assert offset.pose_choice.on_model[PoseSource.FITTED] > 0.9
    assert np.allclose(offset.rigid.R, R, atol=1e-2)
    assert any("turn" in w.text and "check the tracker's registration" in w.text for w in offset.warnings)

    lifted, rest_motion = _lifted_lobe(liver, 60.0, 30.0)
    explained = pipeline.register(small_model, lifted)
    assert explained.pose_choice.source is PoseSource.GIVEN_TURN, explained.pose_choice.as_dict()
    fits = explained.pose_choice.fits  # the fit from ICP's pose was the better one by far: not the ratio rule
    assert fits.given_rms_mm > 2 * POSE_RULE.given_ratio * fits.fitted_rms_mm, fits
    assert any(w.text.startswith("ICP's pose is not taken") for w in explained.warnings)
    monkeypatch.setattr(pipeline, "prefer_given",
                        lambda c, f: prefer_given(c, f, replace(POSE_RULE, tracker_turn_deg=180.0)))
    assert rest_motion(explained) < 0.5 * rest_motion(pipeline.register(small_model, lifted))


def test_a_correction_far_beyond_its_uncertainty_is_not_warned_about_from_icps_pose_only():
    """From ICP's pose (the deformable answer shown whatever the verdict) a failed
    cross-validation is not warned about when the correction is at least ``z_strong`` σ; from a
    kept pose (the rigid answer shown) it still is, and an unweighed correction never outweighs."""
    from navapp.registration.support import Support, SupportOptions

    failed = dict(rigid_mm=2.87, deformable_mm=3.12, margin=0.3)  # the demo's first surface-only fit
    strong = Support(**failed, correction_mm=3.41, sigma_mm=0.78)  # z 4.4
    weak = Support(**failed, correction_mm=3.41, sigma_mm=0.90)  # z 3.8
    assert SupportOptions().z_strong == strong.z_strong == 4.0
    assert not strong.supported and strong.outweighs and not weak.outweighs
    assert strong.warning_for(shown_rigid=False) is None
    assert weak.warning_for(shown_rigid=False).startswith("deformation not supported by the data")
    assert strong.warning_for(shown_rigid=True).startswith("deformation not supported by the data")
    assert not Support(**failed).outweighs and Support(**failed).warning_for(shown_rigid=False)
    assert strong.as_dict()["outweighs"] is True and "outweighs" not in Support(**failed).as_dict()


def test_a_small_dent_the_basis_cannot_make_is_not_shown_as_a_correction(small_model, phantoms):
    """A narrow 30 mm dent under a 40 mm scan that covers it, already aligned: the
    deformation fits the dent's rim, so it predicts the held-out blocks over the dent better
    than none and passes the cross-validation, but what it does to the organ is a correction
    of a millimetre or two everywhere, under its own σ: the organ away from the dent, which
    did not move, is moved. Weighed against its σ it is not told apart from none: the kept
    pose is the answer, with one line (the held-out tool case tooltest2-a had been left
    silently worse than no correction this way)."""
    from navapp.registration.pipeline import RobustOptions, register
    from navapp.registration.support import SupportOptions

    data, far_motion = _dented_scan(phantoms[0].liver.vertices, small_model, 30.0, 15.0, far_mm=50.0)
    reg = register(small_model, data)
    s = reg.support
    assert reg.rigid.kept and s is not None
    assert s.predicts  # the cross-validation alone would have shown it
    assert s.correction_mm < s.z * s.sigma_mm and not s.supported and not reg.deformed
    assert far_motion(reg) == 0.0
    assert any(w.text.startswith("deformation not determined by the data: the correction it makes")
               for w in reg.warnings)
    assert s.as_dict()["significant"] is False

    unweighed = register(small_model, data, init=RobustOptions(support=SupportOptions(z=0.0)))
    assert unweighed.deformed and far_motion(unweighed) > 1.0


def test_the_load_study_does_not_append_to_a_file_with_other_columns(tmp_path):
    """A results file written before the study's columns grew (``pose``, ``turn_deg``) is not
    appended to with rows that would not line up under its header: one line says so."""
    from navapp.evaluation.loads import COLUMNS, run_loads

    old = tmp_path / "loads.csv"
    old.write_text(",".join(COLUMNS[:-2]) + "\ntool0-a,S,identity,True,True,0.8,0.8,28.69,none,False,,0.0\n")
    with pytest.raises(InputError, match="its columns are not this study's"):
        run_loads([tmp_path / "tool0-b"], old)
    assert old.read_text().count("\n") == 2


def test_an_answer_whose_predicted_error_exceeds_the_margin_says_so(small_model, phantoms, tmp_path):
    """150 points of a lifted right lobe (tip turned 30°, base 15°), already aligned: ICP turns
    the organ about 28° — under the turn no tracker makes — the deformation from there fits
    and is supported, and the rest of the organ, which did not move, is moved over 20 mm.
    No check that compares the answer with simpler ones fires; its predicted error over the
    organ (about 16 mm) is over the 10 mm oncological margin, and one line says so, in the
    warnings and in result.json (``uncertainty.OrganError``). The same scan turned as a
    whole, as a tracker that far off would give, is predicted within the margin: silent."""
    from navapp.registration.pipeline import register
    from navapp.registration.uncertainty import ONCOLOGICAL_MARGIN_MM, OrganError

    liver = phantoms[0].liver.vertices
    data, rest_motion = _lifted_lobe(liver, 30.0, 15.0)
    rng = np.random.default_rng(0)
    scan = {"anterior": data["anterior"][rng.choice(len(data["anterior"]), 150, replace=False)]}
    reg = register(small_model, scan)
    assert reg.deformed and not reg.rigid.kept
    assert rest_motion(reg) > 20.0  # the answer is wrong by tens of mm where nothing moved
    assert isinstance(reg.organ, OrganError) and reg.organ.mean_mm > ONCOLOGICAL_MARGIN_MM
    lines = [w for w in reg.warnings if w.text.startswith("the data do not determine this answer")]
    assert lines == reg.warnings, reg.warnings  # the only line: without it the answer is silent
    assert lines[0].kind is WarningKind.ORGAN_ERROR  # said by the predicted error over the organ
    assert f"{reg.organ.mean_mm:.0f} mm (mean), more than the 10 mm oncological margin" in lines[0].text
    assert reg.organ.as_dict()["exceeds_bound"] and reg.organ.nodes > 100

    front = liver[liver[:, 1] > np.percentile(liver[:, 1], 40)]
    sample = front[rng.choice(len(front), 150, replace=False)]
    whole = register(small_model, {"anterior": sample + [4.0, -3.0, 2.0]})
    assert whole.organ is not None and whole.organ.mean_mm < ONCOLOGICAL_MARGIN_MM
    assert not any(w.text.startswith("the data do not determine this answer") for w in whole.warnings)


def test_a_held_out_gain_under_the_margin_says_the_margin():
    """A deformation that predicts the held-out data better, but by less than the margin, is
    warned with the criterion it failed: "1.11 against 1.44 mm" alone reads as support (the hard
    cases' baseline). One that predicts them worse needs no criterion said."""
    from navapp.registration.support import Support

    under = Support(rigid_mm=1.44, deformable_mm=1.11, margin=0.3).warning_for(shown_rigid=False)
    assert "1.11 mm RMS against 1.44 mm without deformation, 23 % better, under the 30 % asked" in under
    worse = Support(rigid_mm=2.87, deformable_mm=3.12, margin=0.3).warning_for(shown_rigid=False)
    assert "without deformation —" in worse and "%" not in worse
