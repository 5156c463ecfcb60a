import sys, json, trimesh
from navapp.anatomy.meshing import _mesh_with_log, MeshAttempt
from navapp.errors import NavappError
edge = float(sys.argv[1])
for p in sys.argv[2:]:
    s = trimesh.load(p, process=True)
    for a in (40.0, 60.0, 90.0):
        try:
            _, log = _mesh_with_log(s, edge, 0, None, (MeshAttempt("gmsh", a),))
        except NavappError as e:
            log = [str(e)[:200]]
        print(p, a, json.dumps(log[-1]), flush=True)
