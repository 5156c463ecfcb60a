"""Where a scene's tool presses: its site on the liver, the patch centre, the push direction.

A scene names a site (``anterior``: outward normal facing anterior, n_y > 0.3;
``inferior``: facing inferior, n_z < −0.5, the visceral face) and a point near it; the
centre is the site's boundary node nearest that point and the tool pushes against the
mean outward normal of the boundary around it (within the tip's radius), so a tip on a
curved border pushes into the organ, not along it.
"""

import numpy as np

from ..anatomy.meshing import TetMesh
from ..errors import InputError
from .scene import ToolSpec
from .truth import Tool, ToolLoad, outward_normals

SITE_NORMALS = {"anterior": (1, 0.3), "inferior": (2, -0.5)}  # (axis, threshold): n_y > 0.3, n_z < -0.5


def site_nodes(mesh: TetMesh, site: str) -> tuple[np.ndarray, np.ndarray]:
    """Boundary nodes (S,) of a tool site and their outward normals (S, 3)."""
    s, n = outward_normals(mesh)
    axis, threshold = SITE_NORMALS[site]
    on = n[:, axis] > threshold if threshold > 0 else n[:, axis] < threshold
    return s[on], n[on]


def place_tool(mesh: TetMesh, spec: ToolSpec) -> Tool:
    """The truth's ``Tool`` for a scene's ``[tool]`` on this mesh."""
    nodes, normals = site_nodes(mesh, spec.site)
    if not len(nodes):
        raise InputError(f"the liver has no {spec.site} surface to press on")
    at = np.asarray(spec.at, float)
    i = int(np.argmin(np.linalg.norm(mesh.nodes[nodes] - at, axis=1)))
    centre = mesh.nodes[nodes[i]]
    s, n = outward_normals(mesh)
    near = np.linalg.norm(mesh.nodes[s] - centre, axis=1) < spec.radius_mm
    push = -(n[near] * (n[near] @ normals[i] > 0)[:, None]).sum(0)
    push /= np.linalg.norm(push)
    return Tool(tuple(centre), tuple(push), spec.radius_mm, spec.depth_mm, ToolLoad(spec.load))
