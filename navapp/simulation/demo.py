"""The built-in demo case: phantom 0 under a force-driven deformation, with a stylus swath
over the anterior surface, falciform points and the portal-vein contour of one iUS plane.

Honest scope: this is the small, fixed scene that the README's first command runs until
the scene-driven simulator (tracked stylus patterns, 16 iUS planes, effects) exists.
"""

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
PLANE_OFFSETS_MM = (0.0, -40.0, 30.0, -20.0, 15.0, 45.0)  # left-right offsets of the iUS planes, in order


def demo_case(registration_edge=4.0, truth_edge=3.5, seed=0, planes=1, cache_root=None) -> Case:
    """Phantom 0, deformed, with a stylus swath, falciform points and ``planes`` iUS planes."""
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
    # iUS planes: sagittal-ish slices through the deformed liver, spread left to right;
    # each gives the PV and HV contours and the posterior liver surface it cuts
    portal_d = trimesh.Trimesh(moved(preop.portal.vertices), preop.portal.faces, process=False)
    hepatic_d = trimesh.Trimesh(moved(preop.hepatic.vertices), preop.hepatic.faces, process=False)
    liver_mesh_d = trimesh.Trimesh(liver_d, preop.liver.faces, process=False)
    centre = portal_d.vertices.mean(0)
    for dx in PLANE_OFFSETS_MM[:planes]:
        origin = centre + np.array([dx, 0.0, 0.0])
        normal = np.array([1.0, 0.0, 0.2])
        for name, mesh in (("portal_contour", portal_d), ("hepatic_contour", hepatic_d)):
            seg = trimesh.intersections.mesh_plane(mesh, normal, origin)
            if len(seg):
                pts = seg.reshape(-1, 3)[:: max(1, len(seg) // 60)]
                intraop[name] = np.vstack([intraop.get(name, np.zeros((0, 3))), to_tracker(pts)])
        seg = trimesh.intersections.mesh_plane(liver_mesh_d, normal, origin).reshape(-1, 3)
        back = seg[seg[:, 1] < centre[1] - 10]  # the part of the section behind the vessels
        if len(back):
            intraop["posterior"] = np.vstack([intraop.get("posterior", np.zeros((0, 3))),
                                              to_tracker(back[:: max(1, len(back) // 60)])])
    reg_mesh, _ = cached_tetmesh(preop.liver, registration_edge, cache_root)
    x0 = reg_mesh.nodes
    targets = np.column_stack([x0, to_tracker(moved(x0))])
    return Case(preop=preop, intraop=intraop, targets=targets,
                settings={"name": "demo", "units": "mm",
                          "truth": {"model": "linear elastic, gravity, posterior support", "mesh_edge_mm": truth_edge,
                                    "E_pa": TRUTH_MATERIAL.E}})
