import sys, tempfile
import time, numpy as np, trimesh
from pathlib import Path
from navapp.anatomy.meshing import cached_tetmesh
from navapp.mechanics import fem
s = trimesh.load(sys.argv[-1], process=True)
mesh, _ = cached_tetmesh(s, 4.0, Path(tempfile.gettempdir(), 'precompute49-cache'))
for f in (fem._element_strain_operator_coo, fem.element_strain_operator, fem._element_strain_operator_coo, fem.element_strain_operator):
    t = time.process_time(); B = f(mesh.nodes, mesh.tets); print(f.__name__, round(time.process_time() - t, 3))
A = fem._element_strain_operator_coo(mesh.nodes, mesh.tets); B = fem.element_strain_operator(mesh.nodes, mesh.tets)
print([np.array_equal(getattr(A, x), getattr(B, x)) for x in ('indptr', 'indices', 'data')], A.has_canonical_format, B.has_canonical_format)
G = fem.nodal_strain_operator(mesh.nodes, mesh.tets)
np.savez(str(Path(tempfile.gettempdir(), 'precompute49-G.npz')), data=G.data, indices=G.indices, indptr=G.indptr)
