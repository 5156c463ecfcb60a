"""Distances between tracked tools and closed target surfaces, for the live view.

Three questions the navigation view asks many times a second, each answered exactly
(no sampling) and vectorised over the triangles of a target:

- ``signed_distance``: how far is the stylus tip from a target's surface (negative inside);
- ``rectangle_distance``: how far is the ultrasound image, a bounded rectangle in 3D, from
  a target's surface (0 when the image cuts it or lies inside it);
- ``section_polylines``: where the image plane cuts a target, as polylines in the
  image plane's own (u, v) millimetres, for the 2D view.

The per-target wrappers (``tip_distances``, ``plane_distances``, ``plane_sections``)
take any objects with ``surface`` (a closed, outward ``trimesh.Trimesh`` or None for a
point target) and ``centre`` (3,) — ``anatomy.targets.Target``. Units mm throughout.
"""

from dataclasses import dataclass

import numpy as np

from .closest import triangle_weights
from .planes import plane_section


@dataclass(frozen=True)
class ImagePlane:
    """A bounded image rectangle in 3D (mm).

    ``origin`` is the centre of the image's top edge (the probe face), ``u`` the unit
    lateral axis, ``v`` the unit depth axis (orthogonal to ``u``); the image covers
    u ∈ [−width/2, width/2], v ∈ [0, depth]. For navapp's probe (``simulation.probe``):
    ``ImagePlane.from_pose(T, (W − 1)·s, (H − 1)·s)``, and a plane point (u, v) is pixel
    (col, row) = (u / s + (W − 1) / 2, v / s).
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    width_mm: float
    depth_mm: float

    @classmethod
    def from_pose(cls, probe_to_tracker, width_mm: float, depth_mm: float) -> "ImagePlane":
        """From a 4×4 ProbeToTracker pose whose x axis is lateral and z axis depth."""
        T = np.asarray(probe_to_tracker, float)
        return cls(T[:3, 3].copy(), T[:3, 0].copy(), T[:3, 2].copy(), float(width_mm), float(depth_mm))

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    def to_plane(self, points) -> np.ndarray:
        """(N, 3) points → (N, 3) local (u, v, w) mm, w the signed out-of-plane offset."""
        d = np.asarray(points, float) - self.origin
        return np.column_stack([d @ self.u, d @ self.v, d @ self.normal])

    def corners(self) -> np.ndarray:
        """(4, 3) corners in order around the rectangle."""
        h = self.width_mm / 2
        uv = np.array([[-h, 0.0], [h, 0.0], [h, self.depth_mm], [-h, self.depth_mm]])
        return self.origin + uv[:, :1] * self.u + uv[:, 1:] * self.v


# ---------------------------------------------------------------- point ↔ surface

def winding_numbers(points, vertices, faces) -> np.ndarray:
    """Generalised winding number (N,) of a triangle surface about each point: 1 inside a
    closed outward surface, 0 outside (solid angles by Van Oosterom & Strackee)."""
    p = np.atleast_2d(np.asarray(points, float))
    tri = np.asarray(vertices, float)[np.asarray(faces)]  # (F, 3, 3)
    a = tri[None, :, 0] - p[:, None]
    b = tri[None, :, 1] - p[:, None]
    c = tri[None, :, 2] - p[:, None]
    la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
    num = np.einsum("nfi,nfi->nf", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("nfi,nfi->nf", a, b) * lc + np.einsum("nfi,nfi->nf", a, c) * lb
           + np.einsum("nfi,nfi->nf", b, c) * la)
    return np.arctan2(num, den).sum(1) / (2 * np.pi)


def unsigned_distance(points, vertices, faces, chunk=200_000) -> np.ndarray:
    """Exact distance (N,) mm from each point to the nearest triangle (all triangles
    tested; ``chunk`` bounds the point × triangle pairs held at once)."""
    p = np.atleast_2d(np.asarray(points, float))
    tri = np.asarray(vertices, float)[np.asarray(faces)]
    F = len(tri)
    step = max(1, chunk // F)
    out = np.empty(len(p))
    for i in range(0, len(p), step):
        q = p[i:i + step]
        _, d2 = triangle_weights(np.repeat(q, F, axis=0), np.tile(tri, (len(q), 1, 1)))
        out[i:i + step] = np.sqrt(d2.reshape(len(q), F).min(1))
    return out


def signed_distance(points, vertices, faces) -> np.ndarray:
    """Signed distance (N,) mm from points to a closed surface: negative inside."""
    d = unsigned_distance(points, vertices, faces)
    inside = winding_numbers(points, vertices, faces) > 0.5
    return np.where(inside, -d, d)


# ---------------------------------------------------------------- rectangle ↔ surface

def _point_rectangle(points, plane: ImagePlane) -> np.ndarray:
    """Distance (N,) from points to the filled rectangle."""
    loc = plane.to_plane(points)
    h = plane.width_mm / 2
    du = loc[:, 0] - np.clip(loc[:, 0], -h, h)
    dv = loc[:, 1] - np.clip(loc[:, 1], 0.0, plane.depth_mm)
    return np.sqrt(du * du + dv * dv + loc[:, 2] ** 2)


def segment_distances(p1, q1, p2, q2) -> np.ndarray:
    """Distance (N,) between segments p1q1 and p2q2 (all (N, 3)); Ericson §5.1.9."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    f = np.einsum("ij,ij->i", d2, r)
    c = np.einsum("ij,ij->i", d1, r)
    b = np.einsum("ij,ij->i", d1, d2)
    tiny = 1e-300
    denom = a * e - b * b
    s = np.where(denom > 1e-12 * np.maximum(a * e, tiny), np.clip((b * f - c * e) / np.maximum(denom, tiny), 0, 1), 0.0)
    t = (b * s + f) / np.maximum(e, tiny)
    s = np.where(t < 0, np.clip(-c / np.maximum(a, tiny), 0, 1),
                 np.where(t > 1, np.clip((b - c) / np.maximum(a, tiny), 0, 1), s))
    t = np.clip(t, 0, 1)
    return np.linalg.norm(p1 + s[:, None] * d1 - p2 - t[:, None] * d2, axis=1)


def _clip_hits(seg_uv, h, depth) -> np.ndarray:
    """(S,) bool: does each 2D segment (S, 2, 2) touch the box [−h, h] × [0, depth]
    (Liang–Barsky)."""
    p0, d = seg_uv[:, 0], seg_uv[:, 1] - seg_uv[:, 0]
    t0, t1 = np.zeros(len(p0)), np.ones(len(p0))
    ok = np.ones(len(p0), bool)
    for k, lo, hi in ((0, -h, h), (1, 0.0, depth)):
        for pk, qk in ((-d[:, k], p0[:, k] - lo), (d[:, k], hi - p0[:, k])):
            par = np.abs(pk) < 1e-300
            ok &= ~(par & (qk < 0))
            with np.errstate(divide="ignore", invalid="ignore"):
                r = qk / pk
            t0 = np.where(~par & (pk < 0), np.maximum(t0, r), t0)
            t1 = np.where(~par & (pk > 0), np.minimum(t1, r), t1)
    return ok & (t0 <= t1)


def rectangle_distance(plane: ImagePlane, vertices, faces) -> float:
    """Distance (mm) from the image rectangle to a closed surface; 0 when the rectangle
    cuts the surface or lies wholly inside it.

    Exact: two disjoint convex polygons are nearest at a vertex–polygon or edge–edge pair,
    so for each candidate triangle the minimum of its vertices to the rectangle, the
    rectangle's corners to it and the 3 × 4 edge pairs is taken. Candidates: every point
    of a triangle lies within its longest edge of a vertex, so only triangles with a
    vertex within (nearest vertex distance + longest edge) can hold the minimum.
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces)
    seg = plane_section(v, f, plane.origin, plane.normal)
    if len(seg):
        uv = np.stack([(seg - plane.origin) @ plane.u, (seg - plane.origin) @ plane.v], axis=-1)
        if _clip_hits(uv, plane.width_mm / 2, plane.depth_mm).any():
            return 0.0
    corners = plane.corners()
    if winding_numbers(corners[:1], v, f)[0] > 0.5:
        return 0.0  # the image lies inside the target (no crossing, one corner inside)
    dv = _point_rectangle(v, plane)
    edge = np.linalg.norm(v[f] - v[np.roll(f, 1, axis=1)], axis=2).max()
    near = dv <= dv.min() + edge + 1e-9
    cand = f[near[f].any(1)]
    tri = v[cand]  # (C, 3, 3)
    C = len(tri)
    best = dv[np.unique(cand)].min()
    _, d2 = triangle_weights(np.repeat(corners, C, axis=0), np.tile(tri, (4, 1, 1)))
    best = min(best, float(np.sqrt(d2.min())))
    a = np.repeat(tri, 4, axis=0)  # triangle edges × rectangle edges
    rc = np.tile(corners, (C, 1))
    rn = np.tile(np.roll(corners, -1, axis=0), (C, 1))
    for i in range(3):
        d = segment_distances(a[:, i], a[:, (i + 1) % 3], rc, rn)
        best = min(best, float(d.min()))
    return best


# ---------------------------------------------------------------- plane ∩ surface

def section_polylines(plane: ImagePlane, vertices, faces) -> list[np.ndarray]:
    """The plane's section of a triangle surface as polylines (P, 2) in the plane's
    (u, v) mm. A closed loop repeats its first point at the end; an open surface can
    give open polylines. The whole (unbounded) plane is cut: the view clips to the image.

    The segments are ``geometry.planes.plane_section``'s; they are chained by the mesh
    edge each segment end lies on (exact topology, no tolerance on coordinates).
    """
    seg, edges = plane_section(vertices, faces, plane.origin, plane.normal, return_edges=True)
    if len(seg) == 0:
        return []
    keys, node = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
    node = node.reshape(-1, 2)  # (S, 2): crossing-edge ids of each segment's two ends
    pts3 = np.empty((len(keys), 3))
    pts3[node.ravel()] = seg.reshape(-1, 3)
    uv = np.column_stack([(pts3 - plane.origin) @ plane.u, (pts3 - plane.origin) @ plane.v])
    n = len(keys)
    deg = np.bincount(node.ravel(), minlength=n)  # 2 on a closed manifold, 1 at an open end
    nbr = np.full((n, int(deg.max())), -1)
    fill = np.zeros(n, int)
    for a, b in node.tolist():  # a few hundred at most for a target
        nbr[a, fill[a]] = b
        fill[a] += 1
        nbr[b, fill[b]] = a
        fill[b] += 1
    nbrs = nbr.tolist()
    seen = np.zeros(n, bool)
    lines = []
    # open chains from their ends first, then the loops
    for start in np.flatnonzero(deg == 1).tolist() + list(range(n)):
        if seen[start]:
            continue
        chain, prev, cur = [start], -1, start
        seen[start] = True
        while True:
            nxt = next((x for x in nbrs[cur] if x >= 0 and x != prev and (x == start or not seen[x])), None)
            if nxt is None:
                break
            chain.append(nxt)
            if nxt == start:
                break  # closed loop
            seen[nxt] = True
            prev, cur = cur, nxt
        if len(chain) > 1:
            lines.append(uv[chain])
    return lines


# ---------------------------------------------------------------- per target

def tip_distances(tip, targets) -> np.ndarray:
    """Signed distance (T,) mm from a point (3,) to each target's surface (negative
    inside); a point target (no surface) gives the distance to its centre."""
    tip = np.asarray(tip, float).reshape(1, 3)
    out = np.empty(len(targets))
    for i, t in enumerate(targets):
        if t.surface is None:
            out[i] = float(np.linalg.norm(tip[0] - t.centre))
        else:
            out[i] = signed_distance(tip, t.surface.vertices, t.surface.faces)[0]
    return out


def plane_distances(plane: ImagePlane, targets) -> np.ndarray:
    """Distance (T,) mm from the image rectangle to each target's surface (0 where the
    image cuts or lies in it); a point target gives its centre's distance to the image."""
    out = np.empty(len(targets))
    for i, t in enumerate(targets):
        if t.surface is None:
            out[i] = float(_point_rectangle(np.asarray(t.centre, float).reshape(1, 3), plane)[0])
        else:
            out[i] = rectangle_distance(plane, t.surface.vertices, t.surface.faces)
    return out


def plane_sections(plane: ImagePlane, targets) -> list[list[np.ndarray]]:
    """Per target, its section polylines in the plane's (u, v) mm (``section_polylines``);
    a point target has none."""
    return [[] if t.surface is None else section_polylines(plane, t.surface.vertices, t.surface.faces)
            for t in targets]
