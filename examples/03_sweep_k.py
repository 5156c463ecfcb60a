"""How the number of control points k changes accuracy and time on one case folder.

    python examples/03_sweep_k.py CASE_FOLDER [--ks 15 30 45 60] [--edge 4]

Each k is a new basis (3k modes, paper eq. 3–5; cached after the first run). The paper
uses k = 45; ``results/cost.md`` has the full study.
"""

import argparse
import time

import navapp


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", help="case folder with truth (truth/field.npz or truth/targets.csv)")
    ap.add_argument("--ks", type=int, nargs="+", default=[15, 30, 45, 60], help="values of k")
    ap.add_argument("--edge", type=float, default=navapp.EDGE_MM, help="tet edge length, mm")
    args = ap.parse_args(argv)

    case = navapp.read_case(args.case)
    truth = case.need_truth()  # InputError (one line) without truth
    out = {}
    print(f"{'k':>4} {'TRE mm':>8} {'fit s':>7} {'iterations':>10}")
    for k in args.ks:
        model, _ = navapp.prepare(case, edge=args.edge, k=k)
        x0, x1 = truth.tre_points(model.basis.nodes)  # the same nodes for every k (one edge)
        t = time.perf_counter()
        reg = navapp.register(model, case.intraop)
        seconds = time.perf_counter() - t
        out[k] = navapp.mean_tre(reg.transform(x0), x1)
        print(f"{k:>4} {out[k]:>8.2f} {seconds:>7.2f} {reg.libr.iterations:>10}")
    return out


if __name__ == "__main__":
    main()
