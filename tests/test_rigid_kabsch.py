"""The rigid ICP's update, weighted Kabsch, against trimesh's and scipy's solvers."""

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from navapp.geometry.transforms import kabsch


def _problem(seed, n=60):
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(n, 3)) * [40.0, 25.0, 15.0]
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    Q = P @ R.T + [5.0, -3.0, 12.0] + rng.normal(size=P.shape) * 2.0  # noisy: weights matter
    return P, Q, rng


def _cost(R, t, P, Q, w):
    return float(w @ np.sum((P @ R.T + t - Q) ** 2, axis=1))


def test_equal_and_binary_weights_agree_with_trimesh_procrustes():
    P, Q, rng = _problem(1)
    for w in (np.ones(len(P)), (rng.random(len(P)) < 0.6).astype(float)):
        R, t = kabsch(P, Q, w)
        M = trimesh.registration.procrustes(P, Q, weights=w, reflection=False, scale=False, return_cost=False)
        assert np.allclose(R, M[:3, :3], atol=1e-10) and np.allclose(t, M[:3, 3], atol=1e-8)
        assert np.isclose(np.linalg.det(R), 1.0)


def test_unequal_weights_give_the_weighted_optimum():
    """scipy's align_vectors solves the weighted rotation problem exactly; trimesh weights
    only the centroids, so its rotation has a higher weighted cost."""
    P, Q, rng = _problem(2)
    w = rng.uniform(0.05, 5.0, len(P))
    R, t = kabsch(P, Q, w)
    wn = w / w.sum()
    pc, qc = wn @ P, wn @ Q
    ref, _ = Rotation.align_vectors(Q - qc, P - pc, weights=w)
    assert np.allclose(R, ref.as_matrix(), atol=1e-10)
    assert np.allclose(t, qc - ref.as_matrix() @ pc, atol=1e-8)
    M = trimesh.registration.procrustes(P, Q, weights=w, reflection=False, scale=False, return_cost=False)
    assert _cost(R, t, P, Q, w) < _cost(M[:3, :3], M[:3, 3], P, Q, w)


def test_the_hard_study_removes_the_rigid_part_as_trimesh_does():
    # nonrigid_max (evaluation/hard.py) fits its rigid part with the one Kabsch; the answer is
    # the one trimesh's Procrustes gave it before, and a rigid motion leaves nothing
    from navapp.evaluation.hard import nonrigid_max

    P, _, rng = _problem(7, n=200)
    R = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    rigid = P @ R.T + [4.0, 1.0, -2.0] - P
    assert nonrigid_max(P, rigid) < 1e-9
    u = rigid + 5.0 * np.exp(-np.sum((P - P[0]) ** 2, axis=1) / 400.0)[:, None] * [0.0, 1.0, 0.0]
    T = trimesh.registration.procrustes(P, P + u, reflection=False, translation=True, scale=False, return_cost=False)
    expected = np.linalg.norm(P + u - trimesh.transform_points(P, T), axis=1).max()
    assert nonrigid_max(P, u) > 1.0
    np.testing.assert_allclose(nonrigid_max(P, u), expected, rtol=1e-9)


def test_a_rigid_transform_is_undone_as_numpy_and_scipy_undo_it():
    from navapp.geometry.transforms import apply, apply_inverse, homogeneous, inverse
    from navapp.registration.rigid import RigidResult

    rng = np.random.default_rng(5)
    rot = Rotation.from_rotvec(rng.normal(size=3))
    R, t = rot.as_matrix(), np.array([12.0, -40.0, 7.5])
    T = homogeneous(R, t)
    P = rng.normal(size=(50, 3)) * 60.0
    assert np.allclose(inverse(T), np.linalg.inv(T), atol=1e-12)
    assert np.allclose(inverse(T) @ T, np.eye(4), atol=1e-12)
    Y = apply(T, P)
    expected = rot.inv().apply(Y - t)  # scipy's inverse rotation of the shifted points
    assert np.allclose(apply_inverse(R, t, Y), expected, atol=1e-9)
    assert np.allclose(apply(inverse(T), Y), expected, atol=1e-9)
    assert np.array_equal(RigidResult(R, t, 0, 0.0).inverse(Y), apply_inverse(R, t, Y))
