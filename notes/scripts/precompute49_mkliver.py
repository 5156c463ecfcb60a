"""python mkliver.py PHANTOM ML SPACING OUT.stl [TILT]: a liver as an import of a CT label map makes it."""
import sys, time, numpy as np
from pathlib import Path
from navapp.anatomy.phantom import make_phantom
from navapp.anatomy import ctcase
from navapp.anatomy.labelmaps import StructureMask
from navapp.anatomy.importer import mask_surface, LIVER_SURFACE_EDGE_MM, LIVER_MAX_FACES
from navapp.evaluation.benchmark import scaled_liver
n = int(sys.argv[1]); ml = float(sys.argv[2]); sp = tuple(map(float, sys.argv[3].split(','))); out = sys.argv[4]
tilt = tuple(map(float, sys.argv[5].split(','))) if len(sys.argv) > 5 else ctcase.CT_TILT_DEG
liver = scaled_liver(make_phantom(n).liver, ml)
shape = tuple(int(np.ceil(300/s)) for s in sp)
A = ctcase.grid_affine(liver.bounds.mean(0), sp, shape, tilt)
m = ctcase.voxelise(liver, A, shape)
idx = np.argwhere(m); lo = idx.min(0); hi = idx.max(0) + 1
crop = np.pad(m[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], 1)
S = np.eye(4); S[:3, 3] = lo - 1.0
sm = StructureMask(crop, A @ S, Path(out), 1)
surf = mask_surface(sm, LIVER_SURFACE_EDGE_MM, LIVER_MAX_FACES)
print(len(surf.faces), surf.volume / 1000, surf.is_watertight)
surf.export(out)
