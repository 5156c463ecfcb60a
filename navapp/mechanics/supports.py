"""Where the liver is held: named support regions of a tet mesh's boundary.

One home for the rule that says which boundary nodes a support holds, used by the simulated
truth (``simulation.truth``: zero displacement there) and by the registration's basis when a
case declares its supports (``mechanics.basis``, ``BasisSettings.supports``: every mode
vanishes there). ``"ligaments"``: the posterior bare area, the left and right triangular
ligaments and the falciform attachment, one side released by ``release`` (L, N or R);
``"posterior"``: every boundary node facing posterior (the organ lying on a firm bed);
``"bare_area"``: the bare area alone. The regions are geometric: fractions of the boundary's
bounding box in the preoperative frame (x left–right, y posterior–anterior, z inferior–superior).
"""

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from ..anatomy.meshing import TetMesh
from ..errors import InputError


class Supports(StrEnum):
    """What holds the liver: the simulated truth's supports, and a case's declared ones."""
    LIGAMENTS = "ligaments"  # bare area + triangular ligaments + falciform (``release`` frees one side)
    POSTERIOR = "posterior"  # every boundary node whose outward normal faces posterior
    BARE_AREA = "bare_area"  # the bare area alone (the caval attachment): the lobes swing under a load


RELEASES = ("L", "N", "R")  # the ligament released on the left, none, or on the right


@dataclass(frozen=True)
class HeldSupports:
    """Where a case says its organ is held: case.toml's ``[intraop.supports]`` (``held``,
    ``release``) or ``navapp register --supports``. The registration's basis then vanishes
    there in every mode (``BasisSettings.supports``)."""

    held: Supports
    release: str = "N"  # with ``held = ligaments``: the side released (L, N or R)

    @classmethod
    def parse(cls, held: str, release: str = "N", where=None) -> "HeldSupports":
        """From the words a user wrote; ``where``: the file or option named in the one-line error."""
        if held not in {s.value for s in Supports}:
            raise InputError(f"supports must be one of {', '.join(s.value for s in Supports)}, got {held!r}", where)
        if release not in RELEASES:
            raise InputError(f"the released side must be \"L\", \"N\" or \"R\", got {release!r}", where)
        return cls(Supports(held), release)

    def prepare_args(self) -> dict:
        """``registration.pipeline.prepare``'s keyword arguments."""
        return {"supports": self.held.value, "release": self.release}


def case_supports(settings: dict, where=None) -> HeldSupports | None:
    """A case's declared supports (case.toml ``[intraop.supports]``), None when it declares none
    (the paper's free-floating basis)."""
    table = settings.get("intraop", {}).get("supports")
    if table is None:
        return None
    if "held" not in table:
        raise InputError("[intraop.supports] needs held = \"ligaments\", \"posterior\" or \"bare_area\"", where)
    return HeldSupports.parse(table["held"], table.get("release", "N"), where)


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



def held_nodes(mesh: TetMesh, supports: "Supports | str", release: str = "N") -> np.ndarray:
    """Every node the named supports hold, (H,) sorted unique indices."""
    return np.unique(np.concatenate(list(supported_nodes(mesh, release, Supports(supports)).values())))
