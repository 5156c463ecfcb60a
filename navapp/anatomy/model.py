"""The preoperative model: plain dataclasses at the seam between anatomy and the rest.

Coordinates are millimetres in the preoperative image frame: +x toward the patient's
left, +y anterior, +z superior.
"""

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import trimesh

REGION_NAMES = ("anterior", "posterior", "falciform", "ridge_left", "ridge_right")
"""Liver-surface labels, in the order of their integer codes in ``PreopModel.regions``."""

VESSELS = ("portal", "hepatic")


@dataclass
class Centerline:
    """Ordered polylines of one vessel tree.

    points (P, 3) mm, branch (P,) int: consecutive points with the same branch id form one
    polyline, in order. Tangents are derived, unit length, (P, 3).
    """

    points: np.ndarray
    branch: np.ndarray
    radius: np.ndarray | None = None  # (P,) mm; phantoms know it, case folders need not

    @property
    def tangents(self) -> np.ndarray:
        return polyline_tangents(self.points, self.branch)

    def segments(self) -> np.ndarray:
        """(S, 2) index pairs of consecutive points on the same branch."""
        i = np.flatnonzero(self.branch[1:] == self.branch[:-1])
        return np.column_stack([i, i + 1])


def polyline_tangents(points: np.ndarray, branch: np.ndarray) -> np.ndarray:
    """Unit tangents (P, 3) by central differences within each branch (one-sided at ends)."""
    P = len(points)
    t = np.zeros((P, 3))
    same_next = np.zeros(P, bool)
    same_next[:-1] = branch[1:] == branch[:-1]
    same_prev = np.zeros(P, bool)
    same_prev[1:] = same_next[:-1]
    nxt = np.where(same_next, np.arange(P) + 1, np.arange(P))
    prv = np.where(same_prev, np.arange(P) - 1, np.arange(P))
    t = points[nxt] - points[prv]
    n = np.linalg.norm(t, axis=1)
    bad = n < 1e-12
    t[~bad] /= n[~bad, None]
    t[bad] = 0.0  # a single-point branch has no direction; such points are rejected on read
    return t


@dataclass(eq=False)
class Target:
    """One tumour target (``anatomy.targets`` reads and writes them). ``surface`` a closed
    outward triangle surface (mm) or None for a point target; ``centre`` (3,) mm — the
    surface's volume centroid when read, and the mapped centre when carried through a
    registration; ``source`` the file it came from."""

    name: str
    centre: np.ndarray
    surface: trimesh.Trimesh | None = None
    source: str | None = None

    @cached_property
    def diameter_mm(self) -> float:
        """Largest distance between two points of the surface (0 for a point target)."""
        if self.surface is None:
            return 0.0
        v = np.asarray(self.surface.vertices, float)
        if len(v) > 2000:
            v = np.asarray(self.surface.convex_hull.vertices)  # the farthest pair is on the hull
        d2 = ((v[:, None] - v[None]) ** 2).sum(-1)
        return float(np.sqrt(d2.max()))

    @property
    def volume_ml(self) -> float:
        return 0.0 if self.surface is None else float(self.surface.volume) / 1000.0

    def summary(self) -> dict:
        """JSON-ready: name, centre (mm), diameter (mm), volume (ml), kind."""
        return {"name": self.name, "kind": "point" if self.surface is None else "surface",
                "centre_mm": [round(float(x), 3) for x in self.centre],
                "diameter_mm": round(self.diameter_mm, 2), "volume_ml": round(self.volume_ml, 3)}


@dataclass
class PreopModel:
    """Everything known before surgery. Only ``liver`` is required."""

    liver: trimesh.Trimesh
    portal: trimesh.Trimesh | None = None
    hepatic: trimesh.Trimesh | None = None
    portal_centerline: Centerline | None = None
    hepatic_centerline: Centerline | None = None
    regions: np.ndarray | None = None  # (V,) int codes into REGION_NAMES
    fiducials: np.ndarray | None = None  # (P, 3) mm, row i ↔ row i of intraop/fiducials.csv
    name: str = "liver"
    meta: dict = field(default_factory=dict)
    targets: list[Target] = field(default_factory=list)  # tumours (preop/targets/); empty: none
    support_points: np.ndarray | None = None  # (P, 3) mm, preop/supports.csv: where the organ is held

    def vessel(self, name: str) -> trimesh.Trimesh | None:
        return getattr(self, name)

    def centerline(self, name: str) -> Centerline | None:
        return getattr(self, f"{name}_centerline")

    def region_mask(self, label: str) -> np.ndarray:
        """(V,) bool mask of liver vertices carrying ``label``."""
        if self.regions is None:
            return np.zeros(len(self.liver.vertices), bool)
        return self.regions == REGION_NAMES.index(label)
