"""Local against exact Saint-Venant relaxation of the basis (navapp/mechanics/basis.py).

    python scripts/relaxation_error.py modes [--layers 2 4 6 8] [--volume-ml 2100]
    python scripts/relaxation_error.py tre CASE_DIR... [--layers 6] [--combos 40]

``modes``: phantom 0 at 4 mm (optionally scaled to a volume), k = 45; for each number of
rings, relaxation seconds and the per-mode relative error ‖Ju_local − Ju_exact‖/‖Ju_exact‖
(one value per column of Ju: median and max), printed as a Markdown table.
``tre``: simulated study cases (python scripts/simulate_study.py DIR) registered with the
exact and the local bases at S, S + 3 planes (``--combos`` triples drawn with a fixed seed
out of the 560; 0 = all) and S + all 16; mean TRE per level and the change it makes.
"""

import argparse
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np

from navapp import progress
from navapp.defaults import EDGE_MM, N_PLANES, K


def modes_table(layers, volume_ml=None, edge=EDGE_MM, k=K):
    from navapp.anatomy.meshing import cached_tetmesh
    from navapp.anatomy.phantom import make_phantom
    from navapp.evaluation.benchmark import scaled_liver
    from navapp.mechanics.basis import point_load_modes, relax_modes
    from navapp.mechanics.controlpoints import geodesic_tiles, nodal_areas, place_control_points
    from navapp.mechanics.fem import stiffness

    liver = make_phantom(0).liver
    if volume_ml:
        liver = scaled_liver(liver, volume_ml)
    mesh, _ = cached_tetmesh(liver, edge, Path(tempfile.gettempdir()) / "navapp-relaxation-error")
    faces = mesh.boundary_faces()
    surface = np.unique(faces)
    K = stiffness(mesh.nodes, mesh.tets)
    control = place_control_points(mesh.nodes, surface, k)
    tiles = geodesic_tiles(mesh.nodes, faces, surface, control)
    areas = nodal_areas(mesh.nodes, faces, surface)
    U, R = point_load_modes(K, control, 5.0)
    t = time.perf_counter()
    exact = relax_modes(K, U, R, control, surface, tiles, areas)
    exact_s = time.perf_counter() - t
    norm = np.linalg.norm(exact, axis=0)

    def row(name, J, sec):
        e = np.linalg.norm(J - exact, axis=0) / norm
        return f"| {name} | {sec:.1f} | {np.median(e):.2e} | {e.max():.2e} |"

    print(f"\nPhantom 0{f' scaled to {volume_ml:g} ml' if volume_ml else ''}, {edge:g} mm: {len(mesh.nodes)} nodes, "
          f"{len(surface)} surface nodes, k = {k}\n")
    print("| relaxation | seconds | per-mode error, median | max |\n|---|---|---|---|")
    print(row("none (point-load modes)", U, 0.0))
    for n in layers:
        t = time.perf_counter()
        J = relax_modes(K, U, R, control, surface, tiles, areas, layers=n)
        print(row(f"tile + {n} rings", J, time.perf_counter() - t), flush=True)
    print(f"| exact (whole mesh) | {exact_s:.1f} | 0 | 0 |", flush=True)


def tre_table(case_dirs, layers, combos, edge=EDGE_MM, k=K, seed=0):
    from navapp.anatomy.caseio import read_case
    from navapp.anatomy.meshing import cached_tetmesh
    from navapp.geometry.interpolation import interpolation_matrix
    from navapp.geometry.tre import mean_tre
    from navapp.mechanics.basis import BasisSettings, load_or_compute_basis
    from navapp.registration.model import build_model, usable_data
    from navapp.registration.pipeline import register
    from navapp.registration.rigid import TOL_BEFORE_LIBR, rigid_icp
    from navapp.simulation.levels import data_level

    triples = list(itertools.combinations(range(N_PLANES), 3))
    if combos:
        pick = np.random.default_rng(seed).choice(len(triples), combos, replace=False)
        triples = [triples[i] for i in sorted(pick)]
    variants = {"exact": None, **{f"{n} rings": n for n in layers}}
    tre = {}  # (variant, level) → list of mean TRE, one per registration
    for d in map(Path, case_dirs):
        case = read_case(d)
        mesh, _ = cached_tetmesh(case.preop.liver, edge)
        x0, x1 = case.need_truth().tre_points(mesh.nodes)
        B = interpolation_matrix(mesh.nodes, mesh.tets, x0)
        stylus = data_level(d, "S", case=case)
        scenarios = [("S", stylus)] + [("S+3", data_level(d, "S+planes", planes=p, case=case)) for p in triples]
        scenarios.append(("S+all", data_level(d, "S+planes", planes=range(N_PLANES), case=case)))
        rigid = None
        for name, n in variants.items():
            basis, _ = load_or_compute_basis(mesh, BasisSettings(k=k, relax_layers=n), label=f"{d.name} {name}")
            model = build_model(basis, case.preop, case.preop.fiducials)
            if rigid is None:  # the rigid start sees only the surface mesh, the same for every variant
                rigid = rigid_icp(model, usable_data(model, stylus), tol_mm=TOL_BEFORE_LIBR)
            for level, data in scenarios:
                reg = register(model, data, rigid=rigid)
                tre.setdefault((name, level), []).append(mean_tre(reg.transform(x0, B=B), x1))
        print(f"{d.name}: " + ", ".join(f"{name} S {tre[(name, 'S')][-1]:.2f}" for name in variants), flush=True)
    n_s3 = len(triples)
    print(f"\n{len(case_dirs)} cases; S + 3: {n_s3} plane triples per case; edge {edge:g} mm, k = {k}\n")
    print("| basis | level | mean TRE (mm) | change vs exact: mean | mean abs | max abs |\n|---|---|---|---|---|---|")
    for level in ("S", "S+3", "S+all"):
        ref = np.array(tre[("exact", level)])
        for name in variants:
            v = np.array(tre[(name, level)])
            dv = v - ref
            print(f"| {name} | {level} | {v.mean():.3f} | {dv.mean():+.4f} | {np.abs(dv).mean():.4f} | "
                  f"{np.abs(dv).max():.4f} |")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="what", required=True)
    m = sub.add_parser("modes")
    m.add_argument("--layers", type=int, nargs="+", default=[2, 4, 6, 8])
    m.add_argument("--volume-ml", type=float)
    t = sub.add_parser("tre")
    t.add_argument("cases", nargs="+")
    t.add_argument("--layers", type=int, nargs="+", default=[6])
    t.add_argument("--combos", type=int, default=40)
    args = p.parse_args()
    progress.QUIET = True
    if args.what == "modes":
        modes_table(args.layers, args.volume_ml)
    else:
        tre_table(args.cases, args.layers, args.combos)


if __name__ == "__main__":
    main()
