"""Child process of ``meshing.tetrahedralise``: ``python -m navapp.anatomy.mesh_worker IN OUT``.

Reads the surface and the attempt from IN (.npz), meshes, and writes ``nodes`` and
``tets`` (or ``error``, one line) to OUT. Runs apart so that the parent can kill a mesher
that hangs.
"""

import sys

import numpy as np

from ..errors import NavappError
from .meshing import ftetwild_mesh, gmsh_mesh


def main(src: str, dst: str) -> int:
    with np.load(src) as a:
        v, f, edge, seed = a["vertices"], a["faces"], float(a["edge"]), int(a["seed"])
        method, angle = str(a["method"]), float(a["feature_angle"])
    try:
        if method == "gmsh":
            nodes, tets = gmsh_mesh(v, f, edge, seed, angle)
        elif method == "ftetwild":
            nodes, tets = ftetwild_mesh(v, f, edge)
        else:
            raise NavappError(f"unknown meshing method {method!r}")
        if len(tets) == 0:
            raise NavappError(f"{method} produced no tetrahedra")
    except NavappError as exc:
        np.savez(dst, error=str(exc))
        return 0
    np.savez(dst, nodes=nodes, tets=tets)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
