"""R(θ) = R_x(θx) R_y(θy) R_z(θz) (paper eq. 9; this order everywhere), its derivatives, and the
angle of a rotation matrix."""

import numpy as np


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _drx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[0, 0, 0], [0, -s, -c], [0, c, -s]])


def _dry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, 0, c], [0, 0, 0], [-c, 0, -s]])


def _drz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, -c, 0], [c, -s, 0], [0, 0, 0]])


_last: tuple = (b"", None)  # the last angles asked and their R, replaced whole (threads read either)


def rotation(theta) -> np.ndarray:
    """R(θ) (3, 3). The last angles' R is kept (and a copy handed out): one LM evaluation asks
    for it once per feature and again in the Jacobian (17 times a live update)."""
    theta = np.asarray(theta, float)
    key = theta.tobytes()  # bits, so that −0.0 is not taken for 0.0
    last = _last
    if last[0] == key:
        return last[1].copy()
    tx, ty, tz = theta
    R = _rx(tx) @ _ry(ty) @ _rz(tz)
    globals()["_last"] = (key, R)
    return R.copy()


def rotation_derivatives(theta) -> np.ndarray:
    """(3, 3, 3): ∂R/∂θ_j for j = x, y, z."""
    tx, ty, tz = theta
    Rx, Ry, Rz = _rx(tx), _ry(ty), _rz(tz)
    return np.stack([_drx(tx) @ Ry @ Rz, Rx @ _dry(ty) @ Rz, Rx @ Ry @ _drz(tz)])


def rotation_angle(R) -> float:
    """The angle (radians, 0–π) by which the rotation matrix ``R`` (3, 3) turns, about whatever axis."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
