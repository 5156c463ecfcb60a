"""The built-in demo case: phantom 0 under a force-driven deformation, with a stylus swath
over the anterior surface, falciform points and the portal-vein contour of one iUS plane.

Honest scope: this is the small, fixed scene that the README's first command runs until
the scene-driven simulator (tracked stylus patterns, 16 iUS planes, effects) exists.
"""

from dataclasses import replace

import numpy as np
import trimesh

from ..anatomy.caseio import Case
from ..anatomy.meshing import cached_tetmesh
from ..anatomy.phantom import make_phantom
from ..mechanics.fem import Material
from ..mechanics.interpolation import interpolation_matrix
from ..registration.rotation import rotation
from .truth import Loading, solve_linear

TRUTH_MATERIAL = Material(E=3000.0, nu=0.45)  # Pa: soft, so that gravity gives ~10 mm


def demo_case(registration_edge=4.0, truth_edge=3.5, seed=0, cache_root=None) -> Case:
    rng = np.random.default_rng(seed)
    preop = make_phantom(0)
    truth_mesh, _ = cached_tetmesh(preop.liver, truth_edge, cache_root)
    loading = Loading(gravity_dir=tuple(np.array([0.35, -1.0, -0.2]) / np.linalg.norm([0.35, -1.0, -0.2])))
    u = solve_linear(truth_mesh, loading, TRUTH_MATERIAL)

    def moved(points):
        return points + interpolation_matrix(truth_mesh.nodes, truth_mesh.tets, points) @ u

    # tracker space = preop frame after a rigid misplacement (what ICP must undo)
    R = rotation(np.radians([4.0, -3.0, 5.0]))
    t = np.array([6.0, -4.0, 8.0])

    def to_tracker(p):
        return (p - preop.liver.centroid) @ R.T + preop.liver.centroid + t

    liver_d = moved(preop.liver.vertices)
    ant = preop.region_mask("anterior")
    v = preop.liver.vertices
    # stylus swaths: three bands across the anterior surface
    bands = np.zeros(len(v), bool)
    for x0 in (-60.0, -10.0, 45.0):
        bands |= np.abs(v[:, 0] - x0 + 0.3 * v[:, 2]) < 7.0
    swath = np.flatnonzero(ant & bands)
    swath = rng.choice(swath, size=min(400, len(swath)), replace=False)
    falc = np.flatnonzero(preop.region_mask("falciform"))
    falc = rng.choice(falc, size=min(40, len(falc)), replace=False)
    intraop = {"anterior": to_tracker(liver_d[swath]), "falciform": to_tracker(liver_d[falc])}
    # one iUS plane through the deformed portal vein
    portal_d = trimesh.Trimesh(moved(preop.portal.vertices), preop.portal.faces, process=False)
    origin = portal_d.vertices.mean(0)
    lines = trimesh.intersections.mesh_plane(portal_d, np.array([1.0, 0.0, 0.2]), origin)
    if len(lines):
        pts = lines.reshape(-1, 3)
        intraop["portal_contour"] = to_tracker(pts[:: max(1, len(pts) // 150)])
    reg_mesh, _ = cached_tetmesh(preop.liver, registration_edge, cache_root)
    x0 = reg_mesh.nodes
    targets = np.column_stack([x0, to_tracker(moved(x0))])
    return Case(preop=preop, intraop=intraop, targets=targets,
                settings={"name": "demo", "units": "mm",
                          "truth": {"model": "linear elastic, gravity, posterior support", "mesh_edge_mm": truth_edge,
                                    "E_pa": TRUTH_MATERIAL.E}})
