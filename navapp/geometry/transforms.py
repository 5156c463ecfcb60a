"""Rotations and rigid transforms: the one home of the small pieces every layer needs.

Rotation vectors and axis–angle rotations go through ``scipy.spatial.transform.Rotation``;
4 × 4 homogeneous transforms act on row-vector point arrays, ``x ↦ R x + t``. The solver's
own parametrisation, R(θ) = R_x R_y R_z with its derivatives (paper eq. 9), stays in
``navapp.registration.rotation``: it is the fit's, not a general rotation.
"""

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def rotvec_matrix(w) -> np.ndarray:
    """Rotation vectors → rotation matrices: (3,) → (3, 3), (S, 3) → (S, 3, 3); |w| in radians."""
    return Rotation.from_rotvec(np.asarray(w, float)).as_matrix()


def axis_angle(axis, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about the unit vector ``axis`` (3,)."""
    return rotvec_matrix(np.asarray(axis, float) * angle_rad)


def rotation_between(a, b) -> np.ndarray:
    """(3, 3) the smallest rotation taking the direction ``a`` (3,) to the direction ``b`` (3,)
    (neither need be unit; opposite directions: a half turn about some axis normal to both)."""
    return Rotation.align_vectors([np.asarray(b, float)], [np.asarray(a, float)])[0].as_matrix()


def homogeneous(R, t) -> np.ndarray:
    """(4, 4) transform ``x ↦ R x + t`` from a (3, 3) matrix (a rotation; or any linear map,
    a voxel grid's scaled axes) and a (3,) shift (mm)."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, t
    return m


def interpolate_pose(a, b, f) -> np.ndarray:
    """(4, 4) rigid pose a fraction ``f`` (0 → ``a``, 1 → ``b``) of the way from ``a`` to ``b``
    (each (4, 4) rigid): rotation by slerp, translation linearly."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    rots = Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]]))
    return homogeneous(Slerp([0.0, 1.0], rots)(float(f)).as_matrix(), (1 - f) * a[:3, 3] + f * b[:3, 3])


def apply(T, points) -> np.ndarray:
    """Points (N, 3) mm through a (4, 4) affine ``T``."""
    return np.asarray(points, float) @ T[:3, :3].T + T[:3, 3]


def apply_rigid(R, t, points) -> np.ndarray:
    """Points (N, 3) mm through ``x ↦ R x + t`` (R (3, 3), t (3,) mm): ``x Rᵀ + t`` row by
    row, the arithmetic of ``apply`` without building the 4 × 4; ``apply_inverse`` undoes it.
    A rotation about a point c is ``apply_rigid(R, c, points - c)``."""
    return np.asarray(points, float) @ np.asarray(R, float).T + t


def apply_inverse(R, t, points) -> np.ndarray:
    """Points (N, 3) mm through the inverse of the rigid ``x ↦ R x + t`` (R (3, 3) a rotation,
    t (3,) mm): ``(y − t) R``, since R⁻¹ = Rᵀ; no matrix is inverted."""
    return (np.asarray(points, float) - t) @ R


def inverse(T) -> np.ndarray:
    """(4, 4) inverse of a rigid (4, 4) ``T`` (rotation and shift), in closed form:
    ``x ↦ Rᵀ x − Rᵀ t``. Not for an affine with scale or shear (a voxel grid's: use
    ``numpy.linalg.inv``)."""
    R, t = np.asarray(T, float)[:3, :3], np.asarray(T, float)[:3, 3]
    return homogeneous(R.T, -(R.T @ t))


def kabsch(P, Q, w=None) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising Σ w_i |R p_i + t − q_i|² (proper rotation, det R = +1).

    Parameters
    ----------
    P, Q : (N, 3) arrays
        corresponding points, mm: ``Q ≈ P Rᵀ + t``.
    w : (N,) array, optional
        non-negative weights (default all equal).

    Returns
    -------
    R : (3, 3) ndarray
    t : (3,) ndarray, mm

    Why not ``trimesh.registration.procrustes(P, Q, weights=w)``: it weights the centroids
    but not the cross-covariance, so with unequal weights (every feature's w_F / N_F, the
    Huber factors) its rotation is not the weighted optimum, as its docstring says. The
    weighted problem has this closed form; with equal or 0/1 weights both agree (a test
    checks both cases against trimesh and the weighted one against scipy's align_vectors).
    """
    P, Q = np.asarray(P, float), np.asarray(Q, float)
    w = np.ones(len(P)) if w is None else np.asarray(w, float)
    w = w / w.sum()
    pc, qc = w @ P, w @ Q
    H = (P - pc).T @ ((Q - qc) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    return R, qc - R @ pc


def probe_pose(origin, lateral, depth) -> np.ndarray:
    """(4, 4) ProbeToTracker of an ultrasound probe whose face centre is ``origin`` (3,) mm,
    the image's lateral axis along ``lateral`` (orthogonalised against ``depth``), its depth
    axis along ``depth`` and the plane normal ``depth × lateral``: columns x, y, z, origin."""
    z = np.asarray(depth, float) / np.linalg.norm(depth)
    x = np.asarray(lateral, float) - (np.asarray(lateral, float) @ z) * z
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, origin
    return m
