"""Signed-distance-like implicit primitives (negative inside, millimetres).

The phantoms are built as implicit solids and polygonised with marching cubes, which is
what makes every phantom surface watertight and manifold by construction. Distances are
exact for spheres, planes and capsules and approximate (scaled) for ellipsoids; only the
zero level set and the sign matter downstream, plus distances near the surface that are
roughly metric so that blending radii are in mm.
"""

import numpy as np


def ellipsoid(p, centre, radii, rotation=None):
    """Approximate SDF of an ellipsoid. ``p`` (..., 3) mm; returns (...,) mm."""
    q = np.asarray(p, float) - centre
    if rotation is not None:
        q = q @ np.asarray(rotation)  # into the ellipsoid's own axes
    k0 = np.linalg.norm(q / radii, axis=-1)
    return (k0 - 1.0) * np.min(radii)


def halfspace(p, point, normal):
    """Signed distance to the plane through ``point``; positive on the ``normal`` side."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    return (np.asarray(p, float) - point) @ n


def sphere(p, centre, radius):
    return np.linalg.norm(np.asarray(p, float) - centre, axis=-1) - radius


def smooth_union(a, b, k):
    """Polynomial smooth minimum with blend radius ``k`` mm (k = 0: plain min)."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def smooth_intersection(a, b, k):
    return -smooth_union(-a, -b, k)


def smooth_subtraction(a, b, k):
    """``a`` with ``b`` carved out."""
    return smooth_intersection(a, -b, k)


def capsule_distance(p, a, b):
    """Distance (...,) from points ``p`` to segment ab, and the segment parameter t in [0, 1]."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1), t
