"""Tumour targets carried through a registration, and their error against a given truth
(where the truth is, ``anatomy.truth.true_targets``: the solver never reads it).

The targets are mapped by ``Registration.transform`` (rigid pose after eq. 8's
deformation, ``pipeline.deform_points``): this module adds no second implementation of
the deformation, it only feeds it the targets' points (``anatomy.targets.target_points``).
"""


import numpy as np

from ..anatomy.targets import Target, map_targets, target_points
from ..geometry.interpolation import interpolation_matrix
from ..geometry.targets_distance import unsigned_distance
from ..geometry.tre import mean_tre


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


def target_errors(registered: Target, truth: Target) -> dict:
    """Error of one registered target against the truth (mm).

    ``centroid_mm``: distance between the volume centroids of the two surfaces (between
    the points, for a point target); ``mean_vertex_mm``: mean distance of corresponding
    vertices; ``mean_surface_mm``: symmetric mean closest-surface distance (shape
    agreement, blind to sliding along the surface).
    """
    if registered.surface is None or truth.surface is None:
        return {"centroid_mm": round(mean_tre([registered.centre], [truth.centre]), 3)}
    a, b = registered.surface, truth.surface
    d_ab = unsigned_distance(a.vertices, b.vertices, b.faces)
    d_ba = unsigned_distance(b.vertices, a.vertices, a.faces)
    out = {"centroid_mm": round(mean_tre([a.center_mass], [b.center_mass]), 3)}
    if a.vertices.shape == b.vertices.shape:
        out["mean_vertex_mm"] = round(mean_tre(a.vertices, b.vertices), 3)
    out["mean_surface_mm"] = round(float(np.concatenate([d_ab, d_ba]).mean()), 3)
    return out
