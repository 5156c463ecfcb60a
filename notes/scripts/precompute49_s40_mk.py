"""python precompute49_s40_mk.py PHANTOM ML OUT.npz [SPACING]: a liver as navapp's import of its CT label map makes it (ctcase.imported_liver), scaled to ML ml."""
import sys, numpy as np
from navapp.anatomy.phantom import make_phantom
from navapp.anatomy.ctcase import imported_liver
from navapp.evaluation.benchmark import scaled_liver
n, ml, out = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
sp = tuple(map(float, sys.argv[4].split(','))) if len(sys.argv) > 4 else None
liver = scaled_liver(make_phantom(n).liver, ml)
s = imported_liver(liver) if sp is None else imported_liver(liver, sp)
np.savez(out, vertices=s.vertices, faces=s.faces)
print(out, len(s.faces), s.volume/1000, s.is_watertight)
