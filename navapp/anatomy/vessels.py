"""Vessel trees for the phantoms: grown centerlines and their tube surfaces.

Trees grow inside an implicit liver: every centerline point keeps at least its radius
plus ``MARGIN`` mm of parenchyma around it, so vessel surfaces stay inside the liver.
"""

import numpy as np
import trimesh
from skimage.measure import marching_cubes

from . import sdf
from .model import Centerline

MARGIN = 3.0  # mm of parenchyma kept between a vessel wall and the liver surface
STEP = 2.0  # mm between centerline points


def _perpendicular(d, rng):
    a = rng.normal(size=3)
    a -= (a @ d) * d
    return a / np.linalg.norm(a)


def _rotate(v, axis, angle):
    """Rodrigues rotation of v about unit ``axis`` by ``angle`` rad.

    The phantoms' own, not ``geometry.transforms.axis_angle``: SciPy's rotation is the same
    to 4e-16 but the same bits only one time in eighteen, and the difference reaches every
    phantom's centerlines (up to 4e-14 mm), which simulated cases store to the last bit; the
    vessel surfaces, snapped to float32, would not move. ``tests/test_one_home.py`` holds the
    two equal."""
    return v * np.cos(angle) + np.cross(axis, v) * np.sin(angle) + axis * (axis @ v) * (1 - np.cos(angle))


def _grow(fn, p0, d, length, r0, r1, rng, curl=0.04):
    """One branch from p0 along d; stops early where the liver gets too thin.

    Returns points (n, 3) and radii (n,), starting at p0.
    """
    pts, radii = [np.asarray(p0, float)], [r0]
    d = d / np.linalg.norm(d)
    n = max(int(length / STEP), 1)
    for i in range(1, n + 1):
        r = r0 + (r1 - r0) * i / n
        d = d + curl * rng.normal(size=3)
        d /= np.linalg.norm(d)
        p = pts[-1] + STEP * d
        if fn(p[None])[0] > -(r + MARGIN):
            break
        pts.append(p)
        radii.append(r)
    return np.array(pts), np.array(radii)


def _grow_tree(fn, root, direction, lengths, radii, rng, angle=np.radians(34)):
    """Binary tree: generation g has branches of length lengths[g] and radius radii[g]."""
    points: list[np.ndarray] = []
    branch: list[int] = []
    rad: list[float] = []

    def recurse(p0, d, g):
        bid = len({*branch}) if branch else 0
        pts, rr = _grow(fn, p0, d, lengths[g], radii[g], radii[min(g + 1, len(radii) - 1)], rng)
        if len(pts) < 3:
            return
        points.extend(pts)
        rad.extend(rr)
        branch.extend([bid] * len(pts))
        if g + 1 >= len(lengths):
            return
        end, dend = pts[-1], pts[-1] - pts[-2]
        dend /= np.linalg.norm(dend)
        cands = []
        for _ in range(8):
            axis = _perpendicular(dend, rng)
            cands.append((_rotate(dend, axis, angle), _rotate(dend, axis, -angle)))
        scores = [max(fn((end + lengths[g + 1] * np.array(c))[:, :])) for c in cands]
        c1, c2 = cands[int(np.argmin(scores))]
        recurse(end, c1, g + 1)
        recurse(end, c2, g + 1)

    recurse(np.asarray(root, float), np.asarray(direction, float), 0)
    return np.array(points), np.array(branch), np.array(rad)


def _merge(trees):
    pts, br, rad, offset = [], [], [], 0
    for p, b, r in trees:
        if len(p) == 0:
            continue
        pts.append(p)
        br.append(b + offset)
        rad.append(r)
        offset += b.max() + 1
    return Centerline(np.vstack(pts), np.concatenate(br), np.concatenate(rad))


def grow_portal_tree(shape, rng) -> Centerline:
    """Portal vein: a trunk entering at the hilum, splitting into right and left systems,
    each branching for three more generations (radii 7 → 3 mm)."""
    h = np.array(shape.hilum_centre)
    root = h + np.array([0.0, 0.0, shape.hilum_radius + 7.0 + MARGIN + 1.0])
    trunk, _ = _grow(shape, root, np.array([0.0, -0.25, 1.0]), 14.0, 7.0, 6.5, rng, curl=0.0)
    fork = trunk[-1]
    lengths, radii = [48.0, 34.0, 24.0, 16.0], [5.8, 4.6, 3.7, 3.0]
    right = _grow_tree(shape, fork, np.array([-1.0, 0.1, 0.35]), lengths, radii, rng)
    left = _grow_tree(shape, fork, np.array([1.0, 0.35, 0.15]), lengths, radii, rng)
    return _merge([(trunk, np.zeros(len(trunk), int), np.linspace(7.0, 6.5, len(trunk))), right, left])


def grow_hepatic_tree(shape, rng) -> Centerline:
    """Hepatic veins: right, middle and left veins converging superior-posteriorly at the
    caval confluence, each branching for two more generations (radii 6.5 → 3 mm)."""
    x0, y0 = -6.0, shape.posterior_y + 24.0
    zs = np.linspace(70, -20, 181)
    pts = np.column_stack([np.full_like(zs, x0), np.full_like(zs, y0), zs])
    deep = np.flatnonzero(shape(pts) < -(6.5 + MARGIN + 4.0))
    confluence = pts[deep[0]] if len(deep) else np.array([x0, y0, 10.0])
    lengths, radii = [52.0, 30.0, 20.0], [6.5, 4.4, 3.2]
    trees = [
        _grow_tree(shape, confluence, np.array(d, float), lengths, radii, rng)
        for d in ([-1.0, 0.3, -0.35], [0.05, 0.8, -0.6], [1.0, 0.45, -0.2])
    ]
    return _merge(trees)


def tube_surface(cl: Centerline, spacing: float = 1.0) -> trimesh.Trimesh:
    """Watertight surface of the union of tapered capsules along the centerline segments.

    The union is evaluated on a grid of ``spacing`` mm, one local box per segment, and
    polygonised with marching cubes; mild Taubin smoothing removes the voxel steps.
    """
    if cl.radius is None:
        raise ValueError("tube_surface needs the centerline's radii")
    seg = cl.segments()
    rmax = cl.radius.max()
    lo = cl.points.min(0) - rmax - 3 * spacing
    hi = cl.points.max(0) + rmax + 3 * spacing
    shape = np.ceil((hi - lo) / spacing).astype(int) + 1
    field = np.full(shape, 10.0 * rmax)
    for i, j in seg:
        a, b, ra, rb = cl.points[i], cl.points[j], cl.radius[i], cl.radius[j]
        blo = np.floor((np.minimum(a, b) - max(ra, rb) - 2 * spacing - lo) / spacing).astype(int).clip(0)
        bhi = np.ceil((np.maximum(a, b) + max(ra, rb) + 2 * spacing - lo) / spacing).astype(int).clip(None, shape - 1)
        ax = [lo[k] + spacing * np.arange(blo[k], bhi[k] + 1) for k in range(3)]
        g = np.stack(np.meshgrid(*ax, indexing="ij"), -1)
        dist, t = sdf.capsule_distance(g, a, b)
        d = dist - (ra + (rb - ra) * t)
        sl = tuple(slice(blo[k], bhi[k] + 1) for k in range(3))
        field[sl] = np.minimum(field[sl], d)
    verts, faces, _, _ = marching_cubes(field, 0.0, spacing=(spacing,) * 3)
    mesh = trimesh.Trimesh(verts + lo, faces[:, ::-1], process=True)
    parts = mesh.split(only_watertight=True)
    if len(parts) > 1:
        mesh = max(parts, key=lambda m: m.volume)
    trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=-0.53, iterations=6)
    mesh.fix_normals()
    return mesh
