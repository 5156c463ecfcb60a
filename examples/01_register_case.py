"""Register a case folder: read it, build the model, fit, and report the target error.

    python examples/01_register_case.py CASE_FOLDER [--edge 4] [--k 45]

A case folder is the layout of docs/design.md §3 (``preop/liver.ply`` and whatever else you
have: vessels, regions, intraoperative point clouds in ``intraop/``, truth in ``truth/``).
``examples/02_run_scene.py`` writes one from a simulated scene.
"""

import argparse

import navapp


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", help="case folder")
    ap.add_argument("--edge", type=float, default=navapp.EDGE_MM, help="tet edge length, mm")
    ap.add_argument("--k", type=int, default=navapp.K, help="number of control points")
    args = ap.parse_args(argv)

    case = navapp.read_case(args.case)
    model, seconds = navapp.prepare(case, edge=args.edge, k=args.k)
    reg = navapp.register(model, case.intraop)
    print(f"{case.name}: {model.basis.M} nodes, k = {args.k}; "
          f"model {sum(seconds.values()):.1f} s, registration {sum(reg.seconds.values()):.2f} s")
    print(f"LIBR: {reg.libr.iterations} iterations, stopped: {reg.libr.stop_reason}, Ω = {reg.libr.omega:.3g}")
    out = {}
    if case.truth is not None:  # truth: where the model's nodes x0 really are (x1)
        x0, x1 = case.truth.tre_points(model.basis.nodes)
        out = {"rigid": navapp.mean_tre(reg.rigid.apply(x0), x1),
               "deformable": navapp.mean_tre(reg.transform(x0), x1)}
        print(f"mean target error: rigid {out['rigid']:.2f} mm, deformable {out['deformable']:.2f} mm "
              f"({len(x0)} targets)")
    return out


if __name__ == "__main__":
    main()
