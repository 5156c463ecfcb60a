"""Exact plane–triangle-mesh sections."""

import numpy as np


def plane_section(vertices, faces, origin, normal, eps=1e-12, return_faces=False, return_edges=False):
    """Segments (S, 2, 3) where the plane through ``origin`` with ``normal`` cuts the
    triangles. Each triangle with vertices on both sides contributes one segment between
    its two edge crossings (linear interpolation of the signed distances); triangles that
    only touch the plane at a vertex contribute nothing. ``return_faces`` also returns the
    index (S,) of the triangle each segment comes from; ``return_edges`` the mesh edge
    (S, 2, 2) vertex indices, sorted) each segment end lies on, so that segments can be
    chained into polylines by shared edges (``geometry.targets_distance.section_polylines``).
    Returns ``seg``, then the faces and/or edges in that order when asked for.
    """
    v = np.asarray(vertices, float)
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    d = (v - origin) @ n
    d = np.where(np.abs(d) < eps, eps, d)  # a vertex on the plane counts as just above it
    f = np.asarray(faces)
    s = d[f] > 0
    cut = s.any(1) & ~s.all(1)
    f, s = f[cut], s[cut]
    # the lone vertex (alone on its side) and the two others, per cut triangle
    lone = np.where(s.sum(1) == 1, np.argmax(s, 1), np.argmin(s, 1))
    i0 = f[np.arange(len(f)), lone]
    i1 = f[np.arange(len(f)), (lone + 1) % 3]
    i2 = f[np.arange(len(f)), (lone + 2) % 3]
    d0, d1, d2 = d[i0], d[i1], d[i2]
    p1 = v[i0] + (d0 / (d0 - d1))[:, None] * (v[i1] - v[i0])
    p2 = v[i0] + (d0 / (d0 - d2))[:, None] * (v[i2] - v[i0])
    seg = np.stack([p1, p2], axis=1)
    out = [seg]
    if return_faces:
        out.append(np.flatnonzero(cut))
    if return_edges:
        e1 = np.sort(np.column_stack([i0, i1]), axis=1)
        e2 = np.sort(np.column_stack([i0, i2]), axis=1)
        out.append(np.stack([e1, e2], axis=1))
    return tuple(out) if len(out) > 1 else seg
