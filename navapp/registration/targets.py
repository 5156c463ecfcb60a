"""Tumour targets carried through a registration, and their error where truth is known.

The targets are mapped by ``Registration.transform`` (rigid pose after eq. 8's
deformation, ``pipeline.deform_points``): this module adds no second implementation of
the deformation, it only feeds it the targets' points (``anatomy.targets.target_points``).
"""

from pathlib import Path

import numpy as np

from ..anatomy.targets import TARGETS_DIR, Target, map_targets, read_targets, target_points, with_points
from ..geometry.interpolation import interpolation_matrix
from ..geometry.targets_distance import unsigned_distance


def target_interpolation(reg, targets: list[Target]):
    """The interpolation matrix (P × M) of ``target_points(targets)`` in the registration
    mesh: build it once when the same targets are mapped at every LM iteration."""
    basis = reg.model.basis
    return interpolation_matrix(basis.nodes, basis.tets, target_points(targets))


def registered_targets(reg, targets: list[Target], beta=None, B=None, rigid: bool = False) -> list[Target]:
    """The targets where the registration puts them (tracker space, mm).

    ``reg`` a ``pipeline.Registration``; ``beta`` (3k + 6,) a state other than its final
    one (e.g. an iteration's, for the live view); ``B`` from ``target_interpolation``;
    ``rigid``: the rigid pose alone (no deformation). Surfaces keep their triangles;
    each centre is the preoperative centre carried by the same map.
    """
    if rigid:
        return map_targets(targets, reg.rigid.apply)
    return map_targets(targets, lambda p: reg.transform(p, beta, B))


def truth_targets(case_dir, targets: list[Target], case=None, basis=None) -> tuple[list[Target] | None, str]:
    """Where the targets truly are intraoperatively, and how that is known.

    ``truth/targets/`` (the simulator writes the targets deformed by its ground truth)
    wins; otherwise, when ``case.targets`` (truth/targets.csv, x0 → x1) holds the nodes
    of ``basis``'s mesh, the true node displacements are interpolated to the targets
    (linear within each tetrahedron: exact up to the mesh's interpolation error).
    Returns (targets in the order given, source) or (None, reason).
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
    if case is not None and case.targets is not None and basis is not None:
        x0, x1 = case.targets[:, :3], case.targets[:, 3:]
        if x0.shape == basis.nodes.shape and np.allclose(x0, basis.nodes, atol=1e-6):
            p = target_points(targets)
            u = interpolation_matrix(basis.nodes, basis.tets, p) @ (x1 - x0)
            return with_points(targets, p + u), "truth/targets.csv interpolated in the registration mesh"
        return None, "truth/targets.csv is not on this registration mesh"
    return None, "no truth"


def target_errors(registered: Target, truth: Target) -> dict:
    """Error of one registered target against the truth (mm).

    ``centroid_mm``: distance between the volume centroids of the two surfaces (between
    the points, for a point target); ``mean_vertex_mm``: mean distance of corresponding
    vertices; ``mean_surface_mm``: symmetric mean closest-surface distance (shape
    agreement, blind to sliding along the surface).
    """
    if registered.surface is None or truth.surface is None:
        return {"centroid_mm": round(float(np.linalg.norm(registered.centre - truth.centre)), 3)}
    a, b = registered.surface, truth.surface
    d_ab = unsigned_distance(a.vertices, b.vertices, b.faces)
    d_ba = unsigned_distance(b.vertices, a.vertices, a.faces)
    out = {"centroid_mm": round(float(np.linalg.norm(a.center_mass - b.center_mass)), 3)}
    if a.vertices.shape == b.vertices.shape:
        out["mean_vertex_mm"] = round(float(np.linalg.norm(a.vertices - b.vertices, axis=1).mean()), 3)
    out["mean_surface_mm"] = round(float(np.concatenate([d_ab, d_ba]).mean()), 3)
    return out
