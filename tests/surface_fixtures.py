"""Liver-like surfaces navapp did not make: implicit solids polygonised by scikit-image's
marching cubes, trimesh primitives, and damaged copies of them, as users' exports come.

Each function returns a ``trimesh.Trimesh`` in mm (+x left, +y anterior, +z superior). They
are the fixtures of the any-liver tests and of ``scripts/mesh_fixtures.py``; nothing here is
navapp code, so that the mesher is tested on surfaces of another origin.
"""

import numpy as np
import trimesh
from skimage.measure import marching_cubes


def _polygonise(fn, lo, hi, spacing):
    """Zero level set of ``fn`` (negative inside) on a grid: (V, 3) mm, outward faces."""
    # a grid offset by an odd fraction of a voxel never samples exactly 0 on the flat
    # faces, which would give marching cubes zero-area triangles
    lo = np.asarray(lo, float) + 0.313 * spacing
    axes = [np.arange(a, b + spacing, spacing) for a, b in zip(lo, hi, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    values = fn(grid)
    v, f, _, _ = marching_cubes(values, 0.0, spacing=(spacing,) * 3)
    mesh = trimesh.Trimesh(v + lo, f[:, ::-1], process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _ellipsoid(p, c, r):
    return (np.linalg.norm((p - np.asarray(c, float)) / np.asarray(r, float), axis=-1) - 1.0) * min(r)


def sharp_ridged_liver(spacing=1.5) -> trimesh.Trimesh:
    """An ellipsoidal liver cut by an oblique plane with no rounding: a knife-edge
    anterior–inferior ridge where the plane meets the dome (≈ 30° wedge)."""
    def fn(p):
        d = _ellipsoid(p, (0, 0, 0), (110, 80, 75))
        n = np.array([0.0, 0.45, -1.0])
        n /= np.linalg.norm(n)
        return np.maximum(d, (p - np.array([0, 0, -15.0])) @ n)
    return _polygonise(fn, (-120, -90, -85), (120, 90, 85), spacing)


def thin_lobe_liver(thickness=6.0, spacing=1.0) -> trimesh.Trimesh:
    """A right lobe with a flat left lobe ``thickness`` mm thick (thinner than 8 mm)."""
    def fn(p):
        right = _ellipsoid(p, (-30, 0, 0), (70, 60, 55))
        slab = np.maximum(_ellipsoid(p, (60, 0, 20), (75, 55, 60)), np.abs(p[..., 2] - 20) - thickness / 2)
        return np.minimum(right, slab)
    return _polygonise(fn, (-105, -65, -60), (140, 60, 60), spacing)


def genus_one_liver(spacing=1.5) -> trimesh.Trimesh:
    """An ellipsoidal liver pierced by a 15 mm tunnel (genus 1), as a vessel canal would."""
    def fn(p):
        body = _ellipsoid(p, (0, 0, 0), (100, 70, 60))
        tunnel = 15.0 - np.linalg.norm(p[..., [0, 1]] - np.array([20.0, 0.0]), axis=-1)
        return np.maximum(body, tunnel)
    return _polygonise(fn, (-110, -80, -70), (110, 80, 70), spacing)


def other_generator_liver() -> trimesh.Trimesh:
    """The sharp-ridged liver reduced to ~7k vertices by quadric decimation: uneven edges
    (about 1–6 mm) on a sharp ridge, like the surfaces of other segmentation tools."""
    return sharp_ridged_liver(1.0).simplify_quadric_decimation(face_count=14000)


def uneven_liver() -> trimesh.Trimesh:
    """Very uneven triangles, about 1 to 12 mm: the sharp-ridged liver polygonised on a
    grid whose spacing grows geometrically from 1 mm at its right end to 12 mm at its left."""
    def fn(p):
        d = _ellipsoid(p, (0, 0, 0), (110, 80, 75))
        n = np.array([0.0, 0.45, -1.0]) / np.linalg.norm([0.0, 0.45, -1.0])
        return np.maximum(d, (p - np.array([0, 0, -15.0])) @ n)
    steps = np.geomspace(1.0, 12.0, 60)
    x = -120.3 + np.concatenate([[0], np.cumsum(steps)])
    x = x[x < 125]
    y, z = np.arange(-90.3, 91, 3.0), np.arange(-85.3, 86, 3.0)
    grid = np.stack(np.meshgrid(x, y, z, indexing="ij"), axis=-1)
    v, f, _, _ = marching_cubes(fn(grid), 0.0)
    # marching cubes works in index space; map each index coordinate through its axis
    v = np.column_stack([np.interp(v[:, i], np.arange(len(a)), a) for i, a in enumerate((x, y, z))])
    mesh = trimesh.Trimesh(v, f[:, ::-1], process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def inward(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The same surface with every triangle wound inward (negative signed volume)."""
    return trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)


def with_speck(mesh: trimesh.Trimesh, size=0.2) -> trimesh.Trimesh:
    """``mesh`` plus a closed tetrahedral speck ``size`` mm across, 5 mm outside it."""
    speck = trimesh.creation.icosahedron()
    speck.apply_scale(size / speck.extents.max())
    where = mesh.vertices[np.argmax(mesh.vertices[:, 0])] + np.array([5.0, 0, 0])
    speck.apply_translation(where)
    return trimesh.util.concatenate([mesh, speck])


def unmerged(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Triangle soup, as an STL converted without merging: every face its own 3 vertices."""
    v = mesh.vertices[mesh.faces].reshape(-1, 3)
    return trimesh.Trimesh(v, np.arange(len(v)).reshape(-1, 3), process=False)


def with_hole(mesh: trimesh.Trimesh, n=6) -> trimesh.Trimesh:
    """``mesh`` with ``n`` adjacent triangles removed: an open surface."""
    f = mesh.faces
    centre = mesh.vertices[f[0]].mean(axis=0)
    order = np.argsort(np.linalg.norm(mesh.vertices[f].mean(axis=1) - centre, axis=1))
    return trimesh.Trimesh(mesh.vertices, np.delete(f, order[:n], axis=0), process=False)


def two_livers(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Two large disjoint copies: not one liver."""
    other = mesh.copy()
    other.apply_translation([mesh.extents[0] * 1.5, 0, 0])
    return trimesh.util.concatenate([mesh, other])


def self_intersecting(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy of ``mesh`` whose one vertex is pulled through the opposite side."""
    v = mesh.vertices.copy()
    i = int(np.argmax(v[:, 1]))
    v[i] = v[i] - np.array([0, 1.6 * mesh.extents[1], 0])
    return trimesh.Trimesh(v, mesh.faces, process=False)
