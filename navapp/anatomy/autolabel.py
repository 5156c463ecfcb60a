"""Liver-surface region labels for a case that has none (e.g. a 3D Slicer import).

The labels follow the geometry the phantoms use (``phantom.label_regions``), but read it
from the surface alone, in the patient frame given by an anterior (and superior) axis:

- anterior: smoothed outward normal facing anterior and not inferior;
- inferior ridges: the anterior-to-visceral border, i.e. normals turning from the anterior
  face to the inferior (visceral) face, plus the band on both sides of a sharp crease
  between the two faces, on the anterior part of the liver; split left/right at the
  falciform plane (without landmarks, at the middle of the left-right extent, a guess);
- falciform: a band along the surface between two landmark points, when given;
- posterior: everything else (posterior face, bare area, visceral surface).

Parameters were chosen by agreement with the built-in labels of phantoms 0–2; see
``docs/decisions/anatomy.md``, "Automatic labels and centerlines".
"""

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from .model import REGION_NAMES

ANTERIOR, POSTERIOR, FALCIFORM, RIDGE_LEFT, RIDGE_RIGHT = range(len(REGION_NAMES))

# thresholds on the smoothed normal n against the anterior axis a and superior axis s;
# the same cuts the phantoms are labelled with, so that a surface the phantoms resemble
# gets the labels the registration was tuned on
ANTERIOR_MIN_NA = 0.1  # n·a above this faces the laparoscope...
ANTERIOR_MIN_NS = -0.55  # ...unless it faces down (the visceral surface)
TURNING_MIN_NA = 0.15  # the rounded inferior border: facing anterior...
TURNING_NS = (-0.8, -0.2)  # ...and tilted 12–53° below horizontal
VISCERAL_MAX_NS = -0.8  # the visceral (inferior) face
STEEP_MIN_NS = -0.2  # the anterior/lateral face above the border


@dataclass
class RegionLabels:
    """Per-vertex region labels of a liver surface.

    Attributes
    ----------
    codes : np.ndarray
        (V,) int, codes into ``REGION_NAMES`` for each liver vertex.
    warnings : list of str
        What could not be labelled and why (e.g. no falciform landmarks).
    """

    codes: np.ndarray
    warnings: list = field(default_factory=list)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"axis {v} has no direction")
    return v / n


def patient_axes(anterior, superior) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (anterior, superior, left) axes, each (3,).

    ``superior`` is made orthogonal to ``anterior``; left = anterior × superior, so that the
    default axes (0, 1, 0), (0, 0, 1) give left = (1, 0, 0) (+x patient-left).
    """
    a = _unit(anterior)
    s = np.asarray(superior, float).reshape(3)
    s = s - (s @ a) * a
    s = _unit(s)
    return a, s, np.cross(a, s)


def smoothed_normals(mesh: trimesh.Trimesh, radius: float) -> np.ndarray:
    """(V, 3) unit vertex normals averaged (area-weighted) over a ball of ``radius`` mm.

    A ball rather than k rings keeps the smoothing independent of the mesh resolution;
    segmentations from images are stair-stepped, and their raw normals speckle the labels.
    """
    n = np.asarray(mesh.vertex_normals, float)
    if radius <= 0:
        return n.copy()
    v = np.asarray(mesh.vertices, float)
    area = _vertex_area(mesh)
    tree = cKDTree(v)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(len(v))])
    j = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(len(v))])
    W = sp.csr_matrix((area[j], (i, j)), shape=(len(v), len(v)))
    out = W @ n
    norm = np.linalg.norm(out, axis=1)
    bad = norm < 1e-12
    out[~bad] /= norm[~bad, None]
    out[bad] = n[bad]
    return out


def _vertex_area(mesh: trimesh.Trimesh) -> np.ndarray:
    """(V,) mm², a third of the area of each face around a vertex."""
    return np.bincount(mesh.faces.ravel(), np.repeat(mesh.area_faces / 3.0, 3), minlength=len(mesh.vertices))


def _edge_graph(mesh: trimesh.Trimesh, keep: np.ndarray | None = None) -> sp.csr_matrix:
    e = mesh.edges_unique
    w = mesh.edges_unique_length
    if keep is not None:
        ok = keep[e[:, 0]] & keep[e[:, 1]]
        e, w = e[ok], w[ok]
    V = len(mesh.vertices)
    rows, cols = np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])
    return sp.csr_matrix((np.concatenate([w, w]), (rows, cols)), shape=(V, V))


def _near(points: np.ndarray, subset: np.ndarray, d: float) -> np.ndarray:
    """(V,) bool: vertex within ``d`` mm (Euclidean) of any vertex of ``subset`` (bool mask)."""
    if not subset.any():
        return np.zeros(len(points), bool)
    dist, _ = cKDTree(points[subset]).query(points, distance_upper_bound=d)
    return np.isfinite(dist)


def _height(points: np.ndarray, normals: np.ndarray, face: np.ndarray, search: float) -> np.ndarray:
    """(V,) mm: how far each vertex lies off the tangent plane of the nearest ``face`` vertex.

    Near a crease this is how deep a vertex of one face lies beneath the other face's
    continuation, which measures the crease band better than the distance to the other
    face: the visceral face leaves the anterior one at a shallow angle. ``inf`` where no
    face vertex lies within ``search`` mm.
    """
    out = np.full(len(points), np.inf)
    if not face.any():
        return out
    idx = np.flatnonzero(face)
    d, k = cKDTree(points[idx]).query(points, distance_upper_bound=search)
    ok = np.isfinite(d)
    q = idx[k[ok]]
    out[ok] = np.abs(np.einsum("ij,ij->i", points[ok] - points[q], normals[q]))
    return out


def _remove_islands(mesh: trimesh.Trimesh, codes: np.ndarray, min_area: float) -> np.ndarray:
    """Relabel connected patches smaller than ``min_area`` mm² with their neighbours' label.

    Done by repeated majority over mesh edges, only inside the small patches, so that a
    label never grows out of them.
    """
    V = len(codes)
    e = mesh.edges_unique
    area = _vertex_area(mesh)
    rows, cols = np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])
    A = sp.csr_matrix((np.ones(2 * len(e)), (rows, cols)), shape=(V, V))
    codes = codes.copy()
    for _ in range(3):
        same = codes[e[:, 0]] == codes[e[:, 1]]
        g = sp.csr_matrix((np.ones(same.sum()), (e[same, 0], e[same, 1])), shape=(V, V))
        ncomp, comp = connected_components(g, directed=False)
        comp_area = np.bincount(comp, area, minlength=ncomp)
        small = comp_area[comp] < min_area
        if not small.any():
            break
        for _ in range(50):
            votes = np.column_stack([A @ ((codes == c) & ~small) for c in range(len(REGION_NAMES))])
            has = small & (votes.sum(1) > 0)
            if not has.any():
                break
            codes[has] = votes[has].argmax(1)
            small[has] = False
    return codes


def falciform_band(mesh: trimesh.Trimesh, landmarks: np.ndarray, left: np.ndarray,
                   width: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """The falciform band between two landmark points and the plane that splits left/right.

    The ligament runs in a near-sagittal plane: the path follows the surface inside a slab
    around the plane through both landmarks whose normal is ``left`` made orthogonal to
    the landmarks' chord (the slab widens, then goes, when it does not connect them).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Liver surface, V vertices, mm.
    landmarks : np.ndarray
        (2, 3) mm, the two ends of the ligament on (or near) the surface.
    left : np.ndarray
        (3,) unit patient-left axis.
    width : float
        Band width, mm.

    Returns
    -------
    band : np.ndarray
        (V,) bool, vertices of the band.
    plane : np.ndarray
        (4,) the falciform plane (unit normal toward patient-left, offset): a point p is on
        the left where ``p @ plane[:3] > plane[3]``.
    """
    lm = np.asarray(landmarks, float).reshape(2, 3)
    v = np.asarray(mesh.vertices, float)
    chord = lm[1] - lm[0]
    nrm = left - (left @ chord) * chord / max(chord @ chord, 1e-12)
    nrm = nrm / np.linalg.norm(nrm) if np.linalg.norm(nrm) > 1e-9 else left
    plane = np.append(nrm, nrm @ lm.mean(0))
    ends = cKDTree(v).query(lm)[1]
    # a narrow slab: in a wide one the shortest path cuts across the dome to one side
    half = 1.5 * float(mesh.edges_unique_length.mean())
    off = np.abs(v @ nrm - plane[3])
    path = None
    for keep in [off < half * k for k in (1, 2, 4)] + [None]:
        if keep is not None:
            keep[ends] = True
        dist, pred = dijkstra(_edge_graph(mesh, keep), indices=ends[0], return_predecessors=True)
        if np.isfinite(dist[ends[1]]):
            path = [ends[1]]
            while path[-1] != ends[0]:
                path.append(pred[path[-1]])
            break
    if path is None:
        raise ValueError("the falciform landmarks lie on two separate pieces of the liver surface")
    pts = v[np.array(path)]
    # distance to the path's segments, not only its vertices, so the band has no scallops
    seg = np.linspace(0, 1, 5)[:-1]
    dense = np.vstack([pts[:-1] + t * (pts[1:] - pts[:-1]) for t in seg] + [pts[-1:]])
    d, _ = cKDTree(dense).query(v, distance_upper_bound=width / 2)
    return np.isfinite(d), plane


def auto_regions(
    liver: trimesh.Trimesh,
    anterior=(0, 1, 0),
    falciform: np.ndarray | None = None,
    *,
    superior=(0, 0, 1),
    normal_radius: float = 3.0,
    crease_steep: float = 8.0,
    crease_visceral: float = 6.0,
    crease_search: float = 30.0,
    crease_turn_max: float = 8.0,
    ridge_front: float = 0.36,
    falciform_width: float = 10.0,
    min_island_area: float = 40.0,
) -> RegionLabels:
    """Label every liver vertex anterior, posterior, falciform, ridge_left or ridge_right.

    Parameters
    ----------
    liver : trimesh.Trimesh
        Closed liver surface, V vertices, outward normals, mm.
    anterior : array_like
        (3,) the patient's anterior direction in the mesh's frame (need not be unit).
    falciform : np.ndarray or None
        (2, 3) mm, two landmark points at the ends of the falciform ligament (e.g. where it
        meets the inferior border and where it leaves the dome). ``None`` leaves the
        falciform out, with a warning.
    superior : array_like
        (3,) the patient's superior direction; its component along ``anterior`` is ignored.
        Patient-left is anterior × superior.
    normal_radius : float
        Radius (mm) of the ball the vertex normals are averaged over.
    crease_steep, crease_visceral : float
        The crease between the steep (anterior or lateral) face and the visceral face
        belongs to the ridges: a vertex within ``crease_steep`` mm of the visceral face and
        less than ``crease_visceral`` mm beneath the tangent plane of the nearest steep-face
        vertex. The visceral face leaves the steep one at a shallow angle, so measuring depth
        rather than distance lets the band reach further onto it.
    crease_search : float
        How far (mm) to look for the steep face from a visceral vertex.
    crease_turn_max : float
        The crease band is added only within ``crease_steep + crease_visceral`` mm of a
        turning vertex whose turn is abrupt: its distances to the visceral and to the steep
        face sum to less than this (mm). A rounded border (the thin left lobe's) turns over
        a wider band and is a ridge by its normals alone. ``inf`` adds the band everywhere.
    ridge_front : float
        Ridges only on the part of the liver anterior of this fraction of its extent along
        the anterior axis (0 = most posterior point, 1 = most anterior): keeps out the
        hilum and the posterior border.
    falciform_width : float
        Width (mm) of the falciform band.
    min_island_area : float
        Patches of one label smaller than this (mm²) take their neighbours' label.

    Returns
    -------
    RegionLabels
        ``codes`` (V,) int into ``REGION_NAMES`` and a list of warnings.
    """
    warnings = []
    a, s, left = patient_axes(anterior, superior)
    v = np.asarray(liver.vertices, float)
    n = smoothed_normals(liver, normal_radius)
    if liver.is_watertight and liver.volume < 0:
        # every label hangs on the normals pointing out; an inside-out export flips them all
        n = -n
        warnings.append("the liver surface is inside out (negative volume): its normals were flipped")
    na, ns = n @ a, n @ s

    codes = np.full(len(v), POSTERIOR)
    codes[(na > ANTERIOR_MIN_NA) & (ns > ANTERIOR_MIN_NS)] = ANTERIOR

    plane = None
    if falciform is None:
        warnings.append("no falciform landmarks given: the falciform region is left out "
                        "(pass two points where the ligament meets the inferior border and the dome)")
    else:
        off = cKDTree(v).query(np.asarray(falciform, float).reshape(2, 3))[0]
        if off.max() > 10.0:
            warnings.append(f"a falciform landmark lies {off.max():.0f} mm off the liver surface; "
                            "the band starts at the nearest surface point")
        band, plane = falciform_band(liver, falciform, left, falciform_width)
        # the ligament attaches to the anterior/superior surface, not the visceral one
        codes[band & (na + ns > 0.3)] = FALCIFORM

    turning = (na > TURNING_MIN_NA) & (ns > TURNING_NS[0]) & (ns < TURNING_NS[1])
    visceral, steep = ns < VISCERAL_MAX_NS, ns > STEEP_MIN_NS
    crease = _near(v, visceral, crease_steep) & (_height(v, n, steep, crease_search) < crease_visceral)
    if np.isfinite(crease_turn_max):
        # a rounded border turns over a wide band and is a ridge by its normals alone;
        # only where the turn is abrupt does the band around the crease join the ridge.
        # The turn's width at a turning vertex: its distance to one face plus to the other
        abrupt = turning.copy()
        if abrupt.any():
            width = np.full(abrupt.sum(), np.inf)
            if visceral.any() and steep.any():
                q = v[abrupt]
                width = (cKDTree(v[visceral]).query(q, distance_upper_bound=crease_turn_max)[0]
                         + cKDTree(v[steep]).query(q, distance_upper_bound=crease_turn_max)[0])
            abrupt[abrupt] = width < crease_turn_max
        crease &= _near(v, abrupt, crease_steep + crease_visceral)
    depth = v @ a
    lo, hi = depth.min(), depth.max()
    front = depth > lo + ridge_front * (hi - lo)
    ridge = (turning | crease) & front
    if plane is None:
        # no landmark: split at the middle of the left-right extent. A crude guess (the
        # ligament lies within ~5 mm of it on phantoms 0-2); neither the front outline nor
        # the deepest point of the border marked the umbilical notch reliably
        lat = v @ left
        plane = np.append(left, 0.5 * (lat.min() + lat.max()))
        warnings.append("ridges split left/right at the middle of the liver's left-right extent "
                        "(no falciform landmarks): give them for a reliable split")
    is_left = v @ plane[:3] > plane[3]
    codes[ridge & is_left] = RIDGE_LEFT
    codes[ridge & ~is_left] = RIDGE_RIGHT
    if min_island_area > 0:
        codes = _remove_islands(liver, codes, min_island_area)
    return RegionLabels(codes=codes, warnings=warnings)
