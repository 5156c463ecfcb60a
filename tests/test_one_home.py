"""One home per concept (issue 51, item 2): each small concept every layer needs is written once,
and the callers use it. Two kinds of test: each home against an independent computation
(SciPy's ``Rotation``, NumPy by hand), and a scan of navapp's source for the shapes a
hand-written copy takes, so that a module going back to its own copy fails here."""

import ast
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import navapp
from navapp.geometry.transforms import apply, apply_inverse, apply_rigid, homogeneous, rotation_between
from navapp.geometry.tre import TreStats, mean_tre, point_errors, tre_stats

ROOT = Path(navapp.__file__).parent


# ---------------------------------------------------------------- the homes themselves


def test_tre_stats_is_a_typed_summary_of_the_one_point_error():
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(40, 3)) * 50.0
    pred = truth + rng.normal(size=truth.shape) * 2.0
    d = np.sqrt(((pred - truth) ** 2).sum(axis=1))  # by hand
    st = tre_stats(pred, truth)
    assert isinstance(st, TreStats)
    np.testing.assert_allclose(point_errors(pred, truth), d, rtol=1e-15)
    assert st.mean_mm == pytest.approx(d.mean(), rel=1e-14) and st.mean_mm == mean_tre(pred, truth)
    assert st.sd_mm == pytest.approx(np.sqrt(((d - d.mean()) ** 2).mean()), rel=1e-12)
    assert (st.max_mm, st.n) == (d.max(), 40)
    assert st.as_dict() == {"mean_mm": st.mean_mm, "sd_mm": st.sd_mm, "max_mm": st.max_mm, "n": 40}


def test_apply_rigid_is_scipys_rotation_plus_the_shift_and_undone_by_apply_inverse():
    rng = np.random.default_rng(4)
    rot = Rotation.from_rotvec(rng.normal(size=3))
    R, t = rot.as_matrix(), np.array([-20.0, 3.5, 41.0])
    P = rng.normal(size=(30, 3)) * 70.0
    Y = apply_rigid(R, t, P)
    np.testing.assert_allclose(Y, rot.apply(P) + t, atol=1e-12)
    np.testing.assert_allclose(Y, apply(homogeneous(R, t), P), atol=1e-12)
    np.testing.assert_allclose(apply_inverse(R, t, Y), P, atol=1e-12)


def test_a_rigid_results_pose_and_the_studies_moves_are_apply_rigid_bit_for_bit():
    from navapp.evaluation.robustness import offset_transform
    from navapp.registration.rigid import RigidResult

    rng = np.random.default_rng(5)
    R, t = Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3) * 10.0
    P = rng.normal(size=(25, 3)) * 60.0
    assert np.array_equal(RigidResult(R, t, 0, 0.0).apply(P), apply_rigid(R, t, P))
    # the robustness study's offset: a rotation about the pivot, then the shift, drawn as before
    pivot = np.array([5.0, -7.0, 11.0])
    move = offset_transform(np.random.default_rng(9), 20.0, 15.0, pivot)
    draw = np.random.default_rng(9)
    axis = draw.normal(size=3)
    Rr = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(20.0)).as_matrix()
    d = draw.normal(size=3)
    np.testing.assert_allclose(move(P), (P - pivot) @ Rr.T + pivot + 15.0 * d / np.linalg.norm(d), atol=1e-12)


@pytest.mark.parametrize("a, b", [([0, 0, 1], [0.3, 0.2, -0.9]), ([1, 2, 3], [1, 2, 3]), ([0, 0, 1], [0, 0, -2]),
                                  ([2.0, 0, 0], [0, 5.0, 0])])
def test_rotation_between_takes_one_direction_to_the_other_by_the_smallest_turn(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    R = rotation_between(a, b)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-12)
    cos = float(a @ b) / np.linalg.norm(a) / np.linalg.norm(b)
    assert np.linalg.norm(Rotation.from_matrix(R).as_rotvec()) == pytest.approx(np.arccos(np.clip(cos, -1, 1)),
                                                                                abs=1e-9)


def test_the_phantoms_own_rodrigues_is_the_same_rotation_as_scipys():
    """Kept apart (module doc of ``anatomy.vessels``): SciPy's rotation differs from it in the
    last bit, which moves every phantom's centerlines; it must stay the same rotation."""
    from navapp.anatomy.vessels import _perpendicular, _rotate

    rng = np.random.default_rng(6)
    for _ in range(200):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        axis, angle = _perpendicular(d, rng), rng.uniform(-np.pi, np.pi)
        np.testing.assert_allclose(_rotate(d, axis, angle), Rotation.from_rotvec(axis * angle).apply(d),
                                   atol=1e-15)


# ---------------------------------------------------------------- no second copy


def _dotted(node) -> str:
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    return node.id if isinstance(node, ast.Name) else ""


def _scopes(tree):
    """(name, node) of each function, innermost, and of the module's top level."""
    yield "<module>", tree
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node.name, node


def _own_nodes(scope):
    """The nodes of ``scope`` outside its nested functions."""
    todo = list(ast.iter_child_nodes(scope))
    while todo:
        node = todo.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        yield node
        todo.extend(ast.iter_child_nodes(node))


def _is_eye4(node) -> bool:
    return (isinstance(node, ast.Call) and _dotted(node.func) == "np.eye" and len(node.args) == 1
            and isinstance(node.args[0], ast.Constant) and node.args[0].value == 4)


# ``pipeline.Registration``'s checks, and the attributes that hold each one's own line
CHECKS = {"support", "organ", "quality", "determinacy", "pose_choice", "pose_evidence", "forces", "held"}
CHECK_LINES = {"warning", "warning_for", "supports_warning"}


def copies(root: Path) -> set[tuple[str, str, str]]:
    """(module, scope, what) for every hand-written copy of a concept with a home."""
    found = set()
    for path in sorted(root.rglob("*.py")):
        module = path.relative_to(root).as_posix()
        tree = ast.parse(path.read_text())
        for name, scope in _scopes(tree):
            nodes = list(_own_nodes(scope))
            calls = {_dotted(n.func) for n in nodes if isinstance(n, ast.Call)}
            text = [ast.unparse(n) for n in nodes if isinstance(n, ast.Call)]

            def add(what, module=module, scope_name=name):
                found.add((module, scope_name, what))

            # a 4 × 4 built by hand: np.eye(4) then its rotation or shift set (transforms.homogeneous)
            eye = {t.id for n in nodes if isinstance(n, ast.Assign) and _is_eye4(n.value)
                   for t in n.targets if isinstance(t, ast.Name)}
            for n in nodes:
                if isinstance(n, (ast.Assign, ast.AugAssign)):
                    for t in n.targets if isinstance(n, ast.Assign) else [n.target]:
                        for sub in ast.walk(t):
                            if isinstance(sub, ast.Subscript) and _dotted(sub.value) in eye:
                                add("4x4 by hand")
            # a rotation by hand (transforms.axis_angle, rotation_between; SciPy's Rotation):
            # Rodrigues' cross product and 1 − cos θ, a matrix of sines and cosines, or a
            # frame stacked from cross products
            if "np.cross" in calls and any(isinstance(n, ast.BinOp) and isinstance(n.op, ast.Sub)
                                           and isinstance(n.left, ast.Constant) and n.left.value == 1
                                           and isinstance(n.right, ast.Call) and _dotted(n.right.func) == "np.cos"
                                           for n in nodes):
                add("rotation by hand")
            for n in nodes:
                if (isinstance(n, ast.Call) and _dotted(n.func) == "np.array" and n.args
                        and isinstance(n.args[0], ast.List) and n.args[0].elts
                        and all(isinstance(e, ast.List) for e in n.args[0].elts)
                        and "np.cos(" in ast.unparse(n) and "np.sin(" in ast.unparse(n)):
                    add("rotation by hand")
                if (isinstance(n, ast.Call) and _dotted(n.func) == "np.column_stack"
                        and "np.cross(" in ast.unparse(n)):
                    add("rotation by hand")
            # a transform applied by hand: x Rᵀ + t, or points in homogeneous coordinates
            # (transforms.apply_rigid, apply)
            for n in nodes:
                if (isinstance(n, ast.BinOp) and isinstance(n.op, ast.Add) and isinstance(n.left, ast.BinOp)
                        and isinstance(n.left.op, ast.MatMult) and isinstance(n.left.right, ast.Attribute)
                        and n.left.right.attr == "T"):
                    add("transform applied by hand")
                if (isinstance(n, ast.Call) and _dotted(n.func) == "np.column_stack"
                        and "np.ones(len(" in ast.unparse(n)):
                    add("transform applied by hand")
            # a rotation vector or axis-angle straight through SciPy (transforms.rotvec_matrix)
            if any(c.endswith("from_rotvec") for c in calls):
                add("rotation vector outside transforms")
            # Kabsch or a polar decomposition: SVD with a determinant's sign (transforms.kabsch)
            if "np.linalg.svd" in calls and "np.linalg.det" in calls:
                add("kabsch by hand")
            # a rename that swaps a file or folder in (outputs.replaced, outputs.replace_folder)
            if "os.replace" in calls or "os.rename" in calls:
                add("atomic replace by hand")
            # a TRE by hand: a norm of differences against the truth (geometry.tre)
            for n in nodes:
                if (isinstance(n, ast.Call) and _dotted(n.func) == "np.linalg.norm" and n.args
                        and isinstance(n.args[0], ast.BinOp) and isinstance(n.args[0].op, ast.Sub)
                        and any(w in ast.unparse(n.args[0]) for w in ("x1", "truth", "true_"))):
                    add("TRE by hand")
            # a data level parsed by hand (simulation.levels)
            if any('.split("+")' in s or ".split('+')" in s or 'startswith("S+")' in s for s in text):
                add("data level parsed by hand")
            # a warning found by its attribute's name (fitwarning.FitWarning)
            if any(s.startswith("getattr(") and "warn" in s for s in text):
                add("warning by getattr")
            # a check's own line read past ``Registration.warnings`` (``pose_doubts``,
            # ``fit_warnings``), which decide which lines stand for the answer shown
            for n in nodes:
                if (isinstance(n, ast.Attribute) and n.attr in CHECK_LINES and isinstance(n.value, ast.Attribute)
                        and n.value.attr in CHECKS):
                    add("a check's line read past Registration")
            # a warning told by its words: ``CARRIED``'s words, or a phrase, searched in a line
            # (a ``FitWarning``'s ``kind`` and ``carried`` say what it is)
            for n in nodes:
                if isinstance(n, ast.Compare) and isinstance(n.ops[0], (ast.In, ast.NotIn)) and (
                        _dotted(n.left) == "CARRIED" or (isinstance(n.left, ast.Constant) and isinstance(
                            n.left.value, str) and "warn" in ast.unparse(n.comparators[0]).lower())):
                    add("a warning told by its words")
    return found


# each kept with its reason; anything else found is a copy to replace by the home
KEPT = {
    # the homes themselves
    ("geometry/transforms.py", "homogeneous", "4x4 by hand"),
    ("geometry/transforms.py", "apply", "transform applied by hand"),
    ("geometry/transforms.py", "apply_rigid", "transform applied by hand"),
    ("geometry/transforms.py", "probe_pose", "4x4 by hand"),
    ("geometry/transforms.py", "rotvec_matrix", "rotation vector outside transforms"),
    ("geometry/transforms.py", "kabsch", "kabsch by hand"),
    ("geometry/tre.py", "point_errors", "TRE by hand"),
    ("outputs.py", "replaced", "atomic replace by hand"),
    ("registration/pipeline.py", "warnings", "a check's line read past Registration"),
    ("registration/pipeline.py", "pose_doubts", "a check's line read past Registration"),
    ("registration/pipeline.py", "fit_warnings", "a check's line read past Registration"),
    ("outputs.py", "replace_folder", "atomic replace by hand"),
    # the phantoms' vessel growth: SciPy's rotation differs in the last bit and moves every
    # phantom's centerlines (and every simulated case's files) by rounding
    ("anatomy/vessels.py", "_rotate", "rotation by hand"),
    # the CPD correspondence's rotation nearest an affine matrix (a polar decomposition of one
    # matrix, not a fit of point pairs); its bits are the transposed truths'
    ("simulation/transpose.py", "correspondence", "kabsch by hand"),
    # the principal axes of the data and of the model matched (four sign choices, the one
    # nearest the tracker pose): no fit of point pairs
    ("registration/rigid.py", "start_poses", "kabsch by hand"),
    # the probe's pixel ↔ tracker maps in homogeneous coordinates: through apply() one pixel
    # (a contour's centre, a plane's centerline point in every simulated case) rounds otherwise
    ("simulation/probe.py", "pixels_to_tracker", "transform applied by hand"),
    ("simulation/probe.py", "tracker_to_pixels", "transform applied by hand"),
    # a file already written in the session's sibling folder moved in by one rename
    ("app/session.py", "_complete", "atomic replace by hand"),
}


def test_each_concept_has_one_home():
    found = copies(ROOT)
    assert found - KEPT == set(), "a second home; use the one the comment in copies() names"
    assert KEPT - found == set(), "a kept copy is gone: take it off KEPT"
