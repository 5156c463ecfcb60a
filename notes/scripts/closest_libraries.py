"""Closest points of 2,000 points on the demo liver's deformed surface (12,424 triangles, 12
random β), side by side: navapp's k-d candidates, its refitted hierarchy (``geometry.bvh``),
FCPW, Open3D's RaycastingScene, libigl's AABB, SciPy's cKDTree; every build or refit counted.
The libraries are not navapp's dependencies: ``pip install fcpw libigl open3d embreex`` first
(each is skipped with its error where missing).

    python notes/scripts/closest_libraries.py

Prints CPU ms per search (median) and the largest distance error against the hierarchy's
exact answer (issue 49; docs/decisions/speed.md, "exact closest points by a refitted hierarchy").
"""

import statistics
import time

import numpy as np
from scipy.spatial import cKDTree

from navapp.defaults import EDGE_MM, K
from navapp.geometry import closest as C
from navapp.geometry.bvh import SurfaceHierarchy
from navapp.registration.pipeline import prepare
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import load_scene_data
from navapp.threads import limit_threads

sd = load_scene_data(demo_scene(), edge=EDGE_MM)
model, _ = prepare(sd.case, EDGE_MM, K)
n = model.basis.Ju.shape[1]
rng = np.random.default_rng(0)
feat = model.features["liver"]
F = feat.cells
betas = []
for _ in range(12):
    b = np.zeros(n + 6)
    b[:n] = rng.normal(0, 0.3, n)
    b[n:n + 3] = rng.normal(0, 3, 3)
    b[n + 3:] = rng.normal(0, 0.05, 3)
    betas.append(b)
Xs = [model.positions(feat, b)[1] for b in betas]
idx = rng.integers(0, len(feat.rest), 2000)
noise = rng.normal(0, 1.5, (2000, 3))
Ps = [X[idx] + noise for X in Xs]
h = SurfaceHierarchy(feat.rest, F)


def distances(face, bary, X, P):
    return np.linalg.norm(np.einsum("ij,ijk->ik", bary, X[F[face]]) - P, axis=1)


exact = [distances(*h.closest(P, X, h.refit(X)), X, P) for X, P in zip(Xs, Ps, strict=True)]


def run(name, search, setup=None):
    state = setup() if setup else None
    times, errors = [], []
    for rep in range(3):
        for k, (X, P) in enumerate(zip(Xs, Ps, strict=True)):
            t = time.process_time()
            d = search(X, P, state)
            times.append(time.process_time() - t)
            if rep == 0:
                errors.append(np.max(np.abs(d - exact[k])))
    print(f"{name:60s} CPU ms median {1e3 * statistics.median(times[len(Xs):]):7.2f}  "
          f"max |d - exact| {max(errors):.2e} mm", flush=True)


def kd_candidates(X, P, _):
    vi = C.nearest_vertices(C.vertex_tree(X), P, feat.near)
    return np.linalg.norm(C.closest_on_surface(P, X, F, feat.table, feat.near, nearest=vi)[2] - P, axis=1)


def scipy_candidates(X, P, _):
    vi = C.nearest_vertices(cKDTree(X, balanced_tree=False, compact_nodes=False), P, feat.near)
    return np.linalg.norm(C.closest_on_surface(P, X, F, feat.table, feat.near, nearest=vi)[2] - P, axis=1)


def hierarchy(X, P, _):
    return distances(*h.closest(P, X, h.refit(X)), X, P)


def hierarchy_rebuilt(X, P, _):
    g = SurfaceHierarchy(X, F)
    return distances(*g.closest(P, X, g.refit(X)), X, P)


def fcpw_runs():
    import fcpw

    def scene(V):
        s = fcpw.scene_3D()
        s.set_object_count(1)
        s.set_object_vertices(np.asfortranarray(V, dtype=np.float32), 0)
        s.set_object_triangles(np.asfortranarray(F, dtype=np.int32), 0)
        s.build(fcpw.aggregate_type.bvh_surface_area, True)
        return s

    def query(s, P):
        hits = fcpw.interaction_3D_list()
        s.find_closest_points(np.asfortranarray(P, dtype=np.float32), np.full(len(P), np.inf, dtype=np.float32), hits)
        return np.fromiter((x.d for x in hits), float, len(P))

    def refit(X, P, s):
        s.update_object_vertices(fcpw.float_3D_list(np.asarray(X, dtype=np.float32)), 0)
        s.refit()
        return query(s, P)

    run("fcpw: built once, refit (vertices as a list) + query", refit, lambda: scene(feat.rest))
    run("fcpw: built every time + query", lambda X, P, _: query(scene(X), P))


def open3d_runs():
    import open3d as o3d

    def search(X, P, _):
        sc = o3d.t.geometry.RaycastingScene()
        sc.add_triangles(o3d.core.Tensor(X.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        found = sc.compute_closest_points(o3d.core.Tensor(P.astype(np.float32)))["points"].numpy()
        return np.linalg.norm(found.astype(float) - P, axis=1)

    run(f"Open3D {o3d.__version__}: RaycastingScene built + compute_closest_points", search)


def igl_runs():
    import igl

    faces = F.astype(np.int64)
    run("libigl: point_mesh_squared_distance", lambda X, P, _: np.sqrt(igl.point_mesh_squared_distance(P, X, faces)[0]))

    def aabb(X, P, _):
        tree = igl.AABB()
        tree.init(X, faces)
        return np.sqrt(tree.squared_distance(X, faces, P)[0])

    run("libigl: AABB init + squared_distance", aabb)


with limit_threads(1):
    run("k-d candidates (pykdtree + compiled test)", kd_candidates)
    run("refitted hierarchy (navapp.geometry.bvh): refit + query", hierarchy)
    run("the same hierarchy rebuilt on X every time", hierarchy_rebuilt)
    run("SciPy cKDTree + compiled test", scipy_candidates)
    for runs in (fcpw_runs, open3d_runs, igl_runs):
        try:
            runs()
        except ImportError as e:
            print(f"{runs.__name__}: {e}")
    try:
        from embreex import rtcore_scene

        print("embreex: no point query, only", [a for a in dir(rtcore_scene) if a[0].isupper()])
    except ImportError as e:
        print(f"embreex: {e}")
