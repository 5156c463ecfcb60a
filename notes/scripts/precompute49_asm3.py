import sys, tempfile
import time, numpy as np, trimesh, sys, scipy.sparse as sp
from pathlib import Path
from navapp.mechanics import fem
from navapp.anatomy.meshing import cached_tetmesh
s = trimesh.load(sys.argv[-1], process=True)
mesh, _ = cached_tetmesh(s, 4.0, Path(tempfile.gettempdir(), 'precompute49-cache'))
t = time.process_time(); K = fem.stiffness(mesh.nodes, mesh.tets); dt = time.process_time() - t
print(fem.__file__, round(dt, 3))
if sys.argv[1] == 'save': sp.save_npz(str(Path(tempfile.gettempdir(), 'precompute49-K.npz')), K)
else:
    O = sp.load_npz(str(Path(tempfile.gettempdir(), 'precompute49-K.npz')))
    with fem.coo_assembly():
        t = time.process_time(); C = fem.stiffness(mesh.nodes, mesh.tets); print('coo', round(time.process_time() - t, 3))
    print('coo==old bits', np.array_equal(C.data, O.data) and np.array_equal(C.indices, O.indices))
    print('new pattern', np.array_equal(K.indptr, O.indptr), np.array_equal(K.indices, O.indices), abs(K - O).max() / abs(O).max())
