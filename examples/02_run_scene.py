"""Simulate a scene (a deformed phantom with stylus and iUS data and the truth), then
register it at two of the paper's data levels: stylus only (S) and stylus + iUS planes.

    python examples/02_run_scene.py [SCENE.toml] [--out DIR] [--planes 3]

Without a scene file it runs the study scene ``phantom0-L`` shipped in the package. The
paper-scale settings (3.5 mm truth mesh, 4 mm registration mesh, k = 45) take a few
minutes the first time (everything is cached); ``--truth-edge 8 --edge 12 --k 12`` is a
quick look.
"""

import argparse
from dataclasses import replace
from pathlib import Path

import navapp


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", type=Path, default=None, help="scene TOML (default: phantom0-L)")
    ap.add_argument("--out", type=Path, default=Path("example-case"), help="case folder to write")
    ap.add_argument("--planes", type=int, default=3, help="iUS planes used at the second level")
    ap.add_argument("--truth-edge", type=float, default=None, help="truth mesh edge, mm (default: the scene's)")
    ap.add_argument("--edge", type=float, default=navapp.EDGE_MM, help="registration mesh edge, mm")
    ap.add_argument("--k", type=int, default=navapp.K, help="number of control points")
    args = ap.parse_args(argv)

    scene = navapp.load_scene(args.scene or navapp.scene_dir() / "phantom0-L.toml")
    scene = scene.with_planes(max(scene.planes, args.planes))
    if args.truth_edge:
        scene = replace(scene, mesh_edge_mm=args.truth_edge)
    report = navapp.simulate(scene, args.out)  # its truth: a field on its own mesh
    print(f"{scene.name}: true displacement mean {report['displacement_mm']['mean']} mm, "
          f"max {report['displacement_mm']['max']} mm")

    case = navapp.read_case(args.out)
    model, _ = navapp.prepare(case, edge=args.edge, k=args.k)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)  # the nodes, and where they truly are
    out = {}
    for label, data in (("S", navapp.data_level(args.out, "S", case=case)),
                        (f"S+{args.planes}", navapp.data_level(args.out, "S+planes", range(args.planes), case=case))):
        reg = navapp.register(model, data)
        out[label] = navapp.mean_tre(reg.transform(x0), x1)
        out[f"{label} rigid"] = navapp.mean_tre(reg.rigid.apply(x0), x1)
        print(f"{label:>5}: mean TRE rigid {out[f'{label} rigid']:.2f} mm, deformable {out[label]:.2f} mm")
    return out


if __name__ == "__main__":
    main()
