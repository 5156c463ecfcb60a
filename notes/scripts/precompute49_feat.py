"""python notes/scripts/precompute49_feat.py phantomN | SURFACE.stl ...: feature edges, their length and the patches at 40/60/90 degrees."""
import sys, numpy as np, trimesh
from scipy.sparse.csgraph import connected_components
import scipy.sparse as sp
def stats(s, edge=4.0):
    adj = s.face_adjacency; ang = np.degrees(s.face_adjacency_angles)
    out = {}
    for th in (40, 60, 90):
        feat = ang > th
        keep = adj[~feat]
        G = sp.coo_matrix((np.ones(len(keep)), (keep[:,0], keep[:,1])), shape=(len(s.faces),)*2)
        n, lab = connected_components(G, directed=False)
        areas = np.bincount(lab, s.area_faces, n)
        fe = s.face_adjacency_edges[feat]
        L = np.linalg.norm(s.vertices[fe[:,0]]-s.vertices[fe[:,1]], axis=1).sum() if len(fe) else 0
        out[th] = dict(feat_edges=int(feat.sum()), feat_len=round(float(L),1), patches=n, small=int((areas < 3*edge**2).sum()), min_area=round(float(areas.min()),2))
    return out, np.percentile(ang, [50, 99, 99.9, 100]).round(1)
for p in sys.argv[1:]:
    if p.startswith('phantom'):
        from navapp.anatomy.phantom import make_phantom
        s = make_phantom(int(p[-1])).liver
    else:
        s = trimesh.load(p, process=True)
    print(p, len(s.faces), stats(s))
