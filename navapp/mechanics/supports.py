"""Where the liver is held: named support regions of a tet mesh's boundary.

One home for the rule that says which boundary nodes a support holds, used by the simulated
truth (``simulation.truth``: zero displacement there) and by the registration's basis when a
case declares its supports (``mechanics.basis``, ``BasisSettings.supports``: every mode
vanishes there). ``"ligaments"``: the posterior bare area, the left and right triangular
ligaments and the falciform attachment, one side released by ``release`` (L, N or R);
``"posterior"``: every boundary node facing posterior (the organ lying on a firm bed);
``"bare_area"``: the bare area alone. The regions are geometric: fractions of the boundary's
bounding box in the preoperative frame (x left–right, y posterior–anterior, z inferior–superior).
``"points"`` (a declaration only, no scene's): the boundary within ``POINT_RADIUS_MM`` of each
point of a case's ``preop/supports.csv``.

How firmly (``conditions``): held (zero displacement at the support's nodes), or on springs of a
stiffness k_s (Pa/mm, traction per millimetre of displacement: an elastic foundation, isotropic),
lumped to the nodes as k_s × nodal area (mm²), which gives K's units, Pa·mm. A stiff spring tends
to held, a zero one to free (tests/test_support_springs.py).
"""

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import scipy.sparse as sp

from ..anatomy.caseio import SUPPORTS_FILE
from ..anatomy.meshing import TetMesh
from ..errors import InputError
from .controlpoints import nodal_areas


class Supports(StrEnum):
    """What holds the liver: the simulated truth's supports, and a case's declared ones."""
    LIGAMENTS = "ligaments"  # bare area + triangular ligaments + falciform (``release`` frees one side)
    POSTERIOR = "posterior"  # every boundary node whose outward normal faces posterior
    BARE_AREA = "bare_area"  # the bare area alone (the caval attachment): the lobes swing under a load
    POINTS = "points"  # declared only: the surface around the points of a case's preop/supports.csv


REGIONS = (Supports.LIGAMENTS, Supports.POSTERIOR, Supports.BARE_AREA)  # named regions: a scene's too
POINT_RADIUS_MM = 5.0  # a support point holds the surface nodes this close (and always its nearest)


RELEASES = ("L", "N", "R")  # the ligament released on the left, none, or on the right


@dataclass(frozen=True)
class HeldSupports:
    """Where a case says its organ is held: case.toml's ``[intraop.supports]`` (``held``,
    ``release``) or ``navapp register --supports``. The registration's basis then vanishes
    there in every mode (``BasisSettings.supports``)."""

    held: Supports
    release: str = "N"  # with ``held = ligaments``: the side released (L, N or R)
    stiffness: float | None = None  # Pa/mm: on springs this stiff; None: held (zero displacement)
    points: tuple = ()  # with ``held = points``: ((x, y, z), …) mm, preoperative frame

    @classmethod
    def parse(cls, held: str, release: str = "N", where=None, stiffness=None, points=None,
              points_where=None) -> "HeldSupports":
        """From the words a user wrote; ``where``: the file or option named in the one-line error.
        ``points`` (P, 3) mm: a case's ``preop/supports.csv`` (``points_where``: its path), needed
        by ``held = points`` (another support does not read them)."""
        if held not in {s.value for s in Supports}:
            raise InputError(f"supports must be one of {', '.join(s.value for s in Supports)}, got {held!r}", where)
        if release not in RELEASES:
            raise InputError(f"the released side must be \"L\", \"N\" or \"R\", got {release!r}", where)
        if stiffness is not None and (isinstance(stiffness, bool) or not isinstance(stiffness, (int, float))
                                      or not np.isfinite(stiffness) or stiffness <= 0):
            raise InputError(f"the supports' stiffness must be a positive number of Pa/mm (omit it: held firmly), "
                             f"got {stiffness!r}", where)
        tup: tuple = ()
        if held == Supports.POINTS:
            if points is None or len(points) == 0:
                raise InputError(f"supports held at points need preop/{SUPPORTS_FILE} (x,y,z rows, mm, "
                                 "preoperative frame)", points_where or where)
            tup = tuple(tuple(float(c) for c in p) for p in np.asarray(points, float).reshape(-1, 3))
        return cls(Supports(held), release, None if stiffness is None else float(stiffness), tup)

    def prepare_args(self) -> dict:
        """``registration.pipeline.prepare``'s keyword arguments."""
        out: dict = {"supports": self.held.value, "release": self.release}
        if self.stiffness is not None:
            out["stiffness"] = self.stiffness
        if self.points:
            out["points"] = self.points
        return out

    def as_dict(self) -> dict:
        """What ``result.json`` and a session say of it: held and release, the stiffness and the
        points where given."""
        out: dict = {"held": self.held.value, "release": self.release}
        if self.stiffness is not None:
            out["stiffness_pa_per_mm"] = self.stiffness
        if self.points:
            out["points"] = [list(p) for p in self.points]
        return out


def case_supports(settings: dict, where=None, points=None) -> HeldSupports | None:
    """A case's declared supports (case.toml ``[intraop.supports]``: ``held``, ``release``,
    ``stiffness_pa_per_mm``), None when it declares none (the paper's free-floating basis).
    ``points``: the case's ``preop/supports.csv`` (``PreopModel.support_points``), for
    ``held = "points"``."""
    table = settings.get("intraop", {}).get("supports")
    if table is None:
        return None
    if "held" not in table:
        raise InputError("[intraop.supports] needs held = \"ligaments\", \"posterior\", \"bare_area\" or "
                         "\"points\"", where)
    return HeldSupports.parse(table["held"], table.get("release", "N"), where, table.get("stiffness_pa_per_mm"),
                              points)


def outward_normals(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    """Boundary node indices (S,) and their area-weighted outward unit normals (S, 3)."""
    faces = mesh.boundary_faces()
    s = np.unique(faces)
    tri = mesh.nodes[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros((len(mesh.nodes), 3))
    for a in range(3):
        np.add.at(n, faces[:, a], fn)
    n = n[s]
    return s, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def supported_nodes(mesh: TetMesh, release: str = "N", supports: Supports = Supports.LIGAMENTS) -> dict:
    """Node sets held fixed, by name: bare area, left/right triangular ligaments,
    falciform attachment (as geometric regions of the boundary; see module doc), or
    the posterior-facing boundary (``Supports.POSTERIOR``)."""
    if supports == Supports.POINTS:
        raise ValueError("supports held at points need the points: held_nodes(mesh, \"points\", points=...)")
    if supports == Supports.POSTERIOR:
        s, n = outward_normals(mesh)
        return {"posterior_bed": s[n[:, 1] < -0.5]}
    if supports == Supports.BARE_AREA:
        return {"bare_area": supported_nodes(mesh, release)["bare_area"]}
    faces = mesh.boundary_faces()
    s = np.unique(faces)
    p = mesh.nodes[s]
    lo, hi = p.min(0), p.max(0)
    ext = hi - lo
    rel = (p - lo) / ext
    sets = {
        "bare_area": s[(rel[:, 1] < 0.12) & (rel[:, 2] > 0.35)],
        "left_triangular": s[(rel[:, 0] > 0.82) & (rel[:, 2] > 0.55) & (rel[:, 1] < 0.6)],
        "right_triangular": s[(rel[:, 0] < 0.12) & (rel[:, 2] > 0.6) & (rel[:, 1] < 0.45)],
        "falciform": s[(np.abs(rel[:, 0] - 0.6) < 0.05) & (rel[:, 2] > 0.5) & (rel[:, 1] > 0.6)],
    }
    if release == "L":
        sets.pop("left_triangular")
    elif release == "R":
        sets.pop("right_triangular")
    return sets



def point_nodes(mesh: TetMesh, points, radius: float = POINT_RADIUS_MM) -> np.ndarray:
    """The boundary nodes a support at ``points`` (P, 3) mm holds: those within ``radius`` mm of
    a point, and each point's nearest boundary node. (H,) sorted unique indices."""
    from scipy.spatial import cKDTree

    s = np.unique(mesh.boundary_faces())
    tree = cKDTree(mesh.nodes[s])
    p = np.asarray(points, float).reshape(-1, 3)
    near = [tree.query(p)[1]] + tree.query_ball_point(p, radius).tolist()
    return np.unique(s[np.concatenate([np.asarray(i, int) for i in near])])


def held_nodes(mesh: TetMesh, supports: "Supports | str", release: str = "N", points=()) -> np.ndarray:
    """Every node the declared supports hold, (H,) sorted unique indices: a named region's, or
    with ``supports = "points"`` the surface around ``points`` (P, 3) mm (``point_nodes``)."""
    if Supports(supports) == Supports.POINTS:
        return point_nodes(mesh, points)
    return np.unique(np.concatenate(list(supported_nodes(mesh, release, Supports(supports)).values())))


@dataclass(frozen=True)
class Conditions:
    """A declared support as boundary conditions of the stiffness: ``nodes`` (H,) the support's
    nodes; ``held`` the nodes fixed at zero (all of them held firmly, none on springs);
    ``springs`` (3M × 3M, Pa·mm) the lumped spring stiffness added to K, None when held."""

    nodes: np.ndarray
    held: np.ndarray
    springs: sp.csr_matrix | None = None

    def stiffen(self, K: sp.spmatrix) -> sp.csr_matrix:
        """K with the springs added (K itself when held firmly)."""
        return K.tocsr() if self.springs is None else (K + self.springs).tocsr()


def spring_matrix(mesh: TetMesh, nodes: np.ndarray, stiffness: float) -> sp.csr_matrix:
    """Springs of ``stiffness`` k_s (Pa/mm) at boundary ``nodes`` (H,): diagonal (3M × 3M),
    k_s × the node's lumped area (a third of its boundary triangles', mm²) on each axis."""
    faces = mesh.boundary_faces()
    k = stiffness * nodal_areas(mesh.nodes, faces, np.asarray(nodes, int))
    diag = np.zeros(3 * len(mesh.nodes))
    diag[(3 * np.asarray(nodes, int)[:, None] + np.arange(3)).ravel()] = np.repeat(k, 3)
    return sp.diags(diag, format="csr")


def conditions(mesh: TetMesh, supports: "Supports | str", release: str = "N", points=(),
               stiffness: float | None = None) -> Conditions:
    """The declared support ``supports`` (with ``release``, ``points``) held firmly
    (``stiffness`` None) or on springs of ``stiffness`` Pa/mm."""
    nodes = held_nodes(mesh, supports, release, points)
    if stiffness is None:
        return Conditions(nodes, nodes)
    return Conditions(nodes, np.zeros(0, int), spring_matrix(mesh, nodes, stiffness))
