"""Where preoperative points truly are intraoperatively: a case's truth (``truth/``).

Two kinds, each answering only what it knows:

- ``TruthField`` (``truth/field.npz``, written by the simulator): the true deformation as a
  field — the truth mesh's nodes and tets, its nodal displacement and the tracker offset —
  so the truth is known at *any* preoperative point, by linear interpolation in the truth
  tets, exactly as the simulator moved its own anatomy. It is apart from every registration
  mesh: evaluation asks it at the points it evaluates (a registration model's nodes, a
  tumour's points).
- ``TruthPoints`` (``truth/targets.csv``: x0, y0, z0, x1, y1, z1): measured pairs, a
  preoperative point and where it truly is. Known there and nowhere else; a whole-organ
  TRE is measured at those points whatever the registration mesh.

A folder with both is read as the field (the simulator of before the field wrote a
``targets.csv`` on its own registration mesh's nodes; see docs/decisions/mechanics.md).
"""

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry.interpolation import interpolation_matrix
from ..geometry.transforms import apply
from .targets import TARGETS_DIR, Target, map_targets, read_targets

FIELD_FILE = "field.npz"  # in truth/
POINTS_FILE = "targets.csv"  # in truth/
POINT_COLUMNS = ("x0", "y0", "z0", "x1", "y1", "z1")


@dataclass(frozen=True, eq=False)
class TruthField:
    """The true deformation as a field on its own tet mesh (mm, tracker space after ``offset``).

    Attributes
    ----------
    nodes : (M, 3) float
        the truth mesh's nodes, mm, preoperative frame.
    tets : (T, 4) int
        its tetrahedra (indices into ``nodes``).
    u : (M, 3) float
        the true nodal displacement, mm.
    offset : (4, 4) float
        the tracker offset applied after the deformation (identity for a pre-aligned scene).
    """

    nodes: np.ndarray
    tets: np.ndarray
    u: np.ndarray
    offset: np.ndarray

    source = f"truth/{FIELD_FILE}"

    def displacement(self, points) -> np.ndarray:
        """The true deformation at ``points`` (n, 3) mm, preoperative frame → (n, 3) mm,
        before the tracker offset: linear in the truth tet holding each point (the nearest
        tet's extrapolation just outside, ``geometry.interpolation.barycentric``)."""
        points = np.atleast_2d(np.asarray(points, float))
        return interpolation_matrix(self.nodes, self.tets, points) @ self.u

    def at(self, points) -> np.ndarray:
        """Where preoperative ``points`` (n, 3) mm truly are intraoperatively: (n, 3) mm,
        tracker space (the deformation, then the tracker offset)."""
        points = np.atleast_2d(np.asarray(points, float))
        moved = points + self.displacement(points)
        return apply(self.offset, moved)

    def tre_points(self, nodes) -> tuple[np.ndarray, np.ndarray]:
        """The points a whole-organ TRE is measured at, and where they truly are: the
        registration model's ``nodes`` (M, 3) mm and ``at(nodes)``."""
        nodes = np.asarray(nodes, float)
        return nodes, self.at(nodes)

    def write(self, folder):
        """``truth/field.npz`` in case folder ``folder``: float64, so a read gives the same
        bits; the same field gives the same bytes (no time stamps in the archive), which a
        viewer session's completeness check compares."""
        tdir = Path(folder) / "truth"
        tdir.mkdir(parents=True, exist_ok=True)
        arrays = {"nodes": self.nodes, "tets": self.tets.astype(np.int64), "u": self.u, "offset": self.offset}
        with zipfile.ZipFile(tdir / FIELD_FILE, "w", zipfile.ZIP_DEFLATED) as z:
            for name, arr in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                with z.open(info, "w") as f:
                    np.lib.format.write_array(f, np.ascontiguousarray(arr), allow_pickle=False)


@dataclass(frozen=True, eq=False)
class TruthPoints:
    """Measured truth: preoperative points ``x0`` (T, 3) mm and where they truly are, ``x1``
    (T, 3) mm, tracker space. Known at these points only."""

    x0: np.ndarray
    x1: np.ndarray

    source = f"truth/{POINTS_FILE}"

    def at(self, points) -> np.ndarray:
        """Not known between the measured points: raises InputError (a simulated case
        written before the truth field existed gives its field when simulated again)."""
        raise InputError(f"the truth is known only at {self.source}'s own points, not at others "
                         "(a simulated case: regenerate the case, which writes the truth field)")

    def tre_points(self, nodes=None) -> tuple[np.ndarray, np.ndarray]:
        """(x0, x1): the measured points, whatever registration mesh ``nodes`` is evaluated."""
        return self.x0, self.x1


Truth = TruthField | TruthPoints


def read_field(path) -> TruthField:
    """``truth/field.npz`` → TruthField; InputError naming the file for a malformed one."""
    path = Path(path)
    try:
        with np.load(path) as z:
            nodes, tets, u, offset = (np.asarray(z[k]) for k in ("nodes", "tets", "u", "offset"))
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"not a truth field (nodes, tets, u, offset): {exc}", path) from None
    if nodes.ndim != 2 or nodes.shape[1] != 3 or u.shape != nodes.shape or offset.shape != (4, 4) \
            or tets.ndim != 2 or tets.shape[1] != 4:
        raise InputError(f"shapes nodes {nodes.shape}, tets {tets.shape}, u {u.shape}, offset {offset.shape}; "
                         "expected (M, 3), (T, 4), (M, 3), (4, 4)", path)
    if not (np.isfinite(nodes).all() and np.isfinite(u).all() and np.isfinite(offset).all()):
        raise InputError("non-finite values", path)
    if len(tets) == 0 or tets.min() < 0 or tets.max() >= len(nodes):
        raise InputError("tets index nodes that do not exist", path)
    return TruthField(nodes.astype(float), tets.astype(np.int64), u.astype(float), offset.astype(float))


def true_targets(case_dir, targets: list[Target], truth: Truth | None) -> tuple[list[Target] | None, str]:
    """Where the tumour ``targets`` truly are intraoperatively, and how that is known.

    ``truth/targets/`` (the simulator writes the targets deformed by its ground truth)
    wins; otherwise a truth field is asked at the targets' points. Measured points know
    nothing between them. Returns (targets in the order given, source) or (None, reason).
    """
    if not targets:
        return None, "no targets"
    tdir = Path(case_dir) / "truth" / TARGETS_DIR
    if tdir.is_dir():
        found = {t.name: t for t in read_targets(tdir)}
        missing = [t.name for t in targets if t.name not in found]
        if missing:
            return None, f"truth/{TARGETS_DIR}/ lacks {', '.join(missing)}"
        return [found[t.name] for t in targets], f"truth/{TARGETS_DIR}/"
    if isinstance(truth, TruthField):
        return map_targets(targets, truth.at), truth.source
    if isinstance(truth, TruthPoints):
        return None, f"{truth.source} holds other points than the targets'"
    return None, "no truth"
