"""The ``navapp`` command line. Every user-facing problem ends as one line on stderr
(``navapp: error: …``) and exit status 2, never a traceback."""

import argparse
import json
import os
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

from . import __version__, progress
from .argtypes import address, k_count, positive
from .defaults import EDGE_MM, K
from .errors import CarriedWarning, InputError, NavappError

DEFAULT_TABLE2_CSV = Path("results/table2.csv")
DASK_STUDIES = ("table2", "cost", "robustness")  # the studies that run on a Dask cluster with --scheduler


_port = positive(int, most=65535)


def cmd_phantom(args):
    from .anatomy.caseio import write_preop
    from .anatomy.phantom import make_phantom

    with progress.stage(f"building phantom {args.liver}"):
        model = make_phantom(args.liver)
    write_preop(model, args.out)
    liver = model.liver
    summary = {
        "phantom": args.liver, "out": str(args.out),
        "liver_vertices": len(liver.vertices), "liver_faces": len(liver.faces),
        "extent_mm": [round(float(x), 1) for x in liver.extents], "volume_ml": round(float(liver.volume) / 1000, 1),
    }
    from .anatomy.model import VESSELS

    for v in VESSELS:  # a phantom has both trees
        cl = model.centerline(v)
        summary[f"{v}_branches"] = int(cl.branch.max() + 1) if cl is not None else 0
    print(json.dumps(summary))


def cmd_mesh(args):
    from .anatomy.caseio import read_case
    from .anatomy.meshing import cached_tetmesh

    case = read_case(args.case)
    _, report = cached_tetmesh(case.preop.liver, args.edge)
    print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in report.items()}))


def cmd_import(args):
    from .anatomy.importer import import_case

    labels = None
    if args.labels:
        try:
            labels = {k.strip(): int(v) for k, v in (item.split("=") for item in args.labels.split(","))}
        except ValueError:
            raise NavappError(f"--labels {args.labels!r}: expected liver=N,portal=N,hepatic=N") from None
    falciform = None
    if args.falciform:
        try:
            falciform = [[float(x) for x in p.split(",")] for p in args.falciform]
        except ValueError:
            raise NavappError("--falciform takes two points X,Y,Z X,Y,Z (mm, in the files' frame)") from None
        if any(len(p) != 3 for p in falciform):
            raise NavappError("--falciform takes two points X,Y,Z X,Y,Z (mm, in the files' frame)")
    centerlines = {v: p for v, p in (("portal", args.portal_centerline), ("hepatic", args.hepatic_centerline)) if p}
    once = {}
    for flag in ("liver", "portal", "hepatic", "labelmap"):
        given = getattr(args, flag) or []
        if len(given) > 1:  # never keep one and drop the other silently
            raise NavappError(f"--{flag} given {len(given)} times ({', '.join(given)}): give each structure once "
                              "(--liver, --portal, --hepatic take one file each)")
        once[flag] = given[0] if given else None
    with progress.stage("importing"):
        rep = import_case(args.out, liver=once["liver"], portal=once["portal"], hepatic=once["hepatic"],
                          labelmap=once["labelmap"], labels=labels, frame=args.frame, falciform=falciform,
                          regions=args.regions, centerlines=centerlines or None, overwrite=args.overwrite,
                          targets=args.target)
    for line in rep.lines:
        print(f"navapp: {line}", file=sys.stderr)
    for line in rep.warnings:
        print(f"navapp: warning: {line}", file=sys.stderr)
    print(json.dumps({"out": str(args.out), "frame": rep.frame, "warnings": len(rep.warnings),
                      "seconds": {k: round(v, 2) for k, v in rep.seconds.items()}}))


def cmd_precompute(args):
    from .anatomy.caseio import read_case
    from .anatomy.meshing import cached_tetmesh
    from .evaluation.benchmark import peak_memory_mb
    from .mechanics.basis import BasisSettings, load_or_compute_basis
    from .mechanics.sparse import backend

    t0 = time.perf_counter()
    case = read_case(args.case)
    mesh, report = cached_tetmesh(case.preop.liver, args.edge)
    surface = len(mesh.surface_nodes())
    if args.k > surface:
        raise NavappError(f"--k {args.k}: more control points than the {surface} surface nodes of the "
                          f"{args.edge:g} mm mesh; use a smaller --k or a finer --edge")
    basis, cached = load_or_compute_basis(mesh, BasisSettings(k=args.k))
    seconds = {"mesh": report["seconds"], **{k: round(v, 3) for k, v in basis.timings.items()}}
    out = {
        "nodes": basis.M, "surface_nodes": len(basis.surface), "k": basis.k, "edge_mm": args.edge,
        "mesher": report["mesher"]["why"] if "mesher" in report else report.get("method"),
        "from_cache": cached, "solver": backend(), "seconds": seconds,
        "total_seconds": round(time.perf_counter() - t0, 3),
        "peak_memory_mb": round(peak_memory_mb(), 1),
    }
    print(json.dumps(out))


def cmd_demo(args):
    from .simulation.scene import demo_scene
    from .simulation.simulate import simulate

    scene = demo_scene()
    if args.truth_edge is not None:
        scene = replace(scene, mesh_edge_mm=args.truth_edge)
    report = simulate(scene, args.out)
    d = report["displacement_mm"]
    print(f"navapp: demo case simulated into {args.out} (true displacement mean {d['mean']} mm, "
          f"max {d['max']} mm); registering it", file=sys.stderr)
    from .registration.cli import cmd_register

    # the register command's own parser gives every option its default: a Namespace written out
    # here by hand fell behind when register gained --local-modes (AttributeError at the end of the demo)
    ns = build_parser().parse_args(["register", "--json", "--edge", repr(args.edge), "--k", str(args.k),
                                    "--", str(args.out)])
    return cmd_register(ns)


def cmd_serve(args):
    from .simulation.scene import demo_scene, load_scene

    scene = load_scene(args.scene) if args.scene else demo_scene()
    from .app.server import serve  # viser is imported only here

    tracking = None
    if args.igtl or args.igtl_config:
        from .tracking.config import TrackingConfig, load_config

        tracking = load_config(args.igtl_config) if args.igtl_config else TrackingConfig()
        if args.igtl:
            host, _, port = args.igtl.rpartition(":")
            if not host or not port.isdigit():
                raise InputError(f"--igtl wants HOST:PORT, not {args.igtl!r}")
            tracking = tracking.with_address(host, int(port))
    slicer = None
    if args.slicer:
        host, _, port = args.slicer.rpartition(":")
        if not port.isdigit() or not 0 < int(port) < 65536:
            raise InputError(f"--slicer wants HOST:PORT or PORT, not {args.slicer!r}")
        slicer = (host or None, int(port))
    from .app.access import decide, tls_context

    serve(scene, args.host, args.port, args.session, args.edge, args.k, view2d_port=args.view2d_port,
          tracking=tracking, slicer=slicer, access=decide(args.host, args.token),
          tls=tls_context(args.certfile, args.keyfile))


def cmd_simulate(args):
    from .simulation.scene import load_scene
    from .simulation.simulate import simulate

    report = simulate(load_scene(args.scene), args.out)
    print(json.dumps(report))


def _check_report_folder(report: Path):
    """Every study writes its report into ``--report`` after its work: a path that cannot be
    that folder (a file, or under one, or where nothing may be written) is refused before any
    work, in one line, instead of a traceback at the end. The folder itself is made by the study."""
    report = Path(report)
    if report.exists() and not report.is_dir():
        raise InputError("--report: not a folder", report)
    parent = report
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"--report: {parent} is not a folder", report)
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"--report: {parent} cannot be written to", report)


def cmd_study(args):
    from .evaluation.report import write_report
    from .evaluation.table2 import run_table2

    _check_report_folder(args.report)
    if args.scheduler:  # before any work: refused by the studies that run locally, checked by the others
        if args.what not in DASK_STUDIES:
            raise NavappError(f"--scheduler: study {args.what} runs on this machine only; --scheduler is for "
                              f"{', '.join(DASK_STUDIES)}")
        from .evaluation.distribute import check_scheduler

        check_scheduler(args.scheduler)
    if args.what == "hard":  # its own phantom model and data: no study cases
        from .evaluation.hard import study_command as hard_command

        return hard_command(args.report, args.edge, args.k)
    cases = _study_cases(args)
    if args.what == "robustness":
        from .evaluation.robustness_report import run_study

        results = _study_results(args)
        if (args.workers or 1) > 1:
            print(f"navapp: {args.workers} robustness cases at once: the per-registration times compete for the "
                  f"cores", file=sys.stderr)
        print(json.dumps(run_study(cases, results, args.report, args.workers or 1, args.quick, args.scheduler,
                                   edge=args.edge, k=args.k)))
        return
    if args.what == "loads":
        from .evaluation.loads import study_command as loads_command

        results = _study_results(args)
        return loads_command(cases, results, args.report, args.workers or 1)
    if args.what == "next-plane":
        from .evaluation.next_plane_study import study_command as next_plane_command

        return next_plane_command(cases, args.results, args.report, args.with_cases, args.with_results,
                                  edge=args.edge, k=args.k)
    if args.what == "error-estimate":
        from .evaluation import error_estimate

        return error_estimate.study_command(cases, args)
    if args.what == "cost":
        from .evaluation.cost import run_cost_study
        from .evaluation.cost_report import write_cost_report

        results = _study_results(args)
        t0 = time.perf_counter()
        # one case at a time unless asked: this study measures time, and cases run side by
        # side compete for the cores (measured: two in parallel doubled the precompute times)
        if (args.workers or 1) > 1:
            print(f"navapp: {args.workers} cost-study cases at once: their timings compete for the cores",
                  file=sys.stderr)
        n = run_cost_study(cases, results, workers=args.workers or 1, quick=args.quick, scheduler=args.scheduler)
        md = write_cost_report(results, args.report)
        print(json.dumps({"rows_added": n, "seconds": round(time.perf_counter() - t0, 1), "results": str(results),
                          "report": str(md)}))
        return
    t0 = time.perf_counter()
    n = run_table2(cases, args.results, workers=args.workers, scheduler=args.scheduler, quick=args.quick,
                   edge=args.edge, k=args.k)
    md = write_report(args.results, args.report, cases)
    print(json.dumps({"registrations_run": n, "seconds": round(time.perf_counter() - t0, 1),
                      "results": str(args.results), "report": str(md)}))


# the studies that append their rows to a results CSV; the others only write a report
APPENDING_STUDIES = ("table2", "cost", "robustness", "loads")


def _study_results(args) -> Path:
    """The CSV a study appends its rows to: --results, or for cost, robustness and loads,
    <report>/<study>.csv when --results is left at Table II's default."""
    if args.what == "table2" or args.results != DEFAULT_TABLE2_CSV:
        return Path(args.results)
    return Path(args.report) / f"{args.what}.csv"


def _study_cases(args):
    """The case folders of a study: --cases, or the study scenes simulated into --case-root
    (the cost study's default is two of them, phantom0-L and phantom2-R)."""
    from .simulation.scene import load_scene
    from .simulation.simulate import simulate

    cases = list(args.cases or [])
    if not cases:
        from .simulation.scene import scene_dir, study_scenes

        scenes = study_scenes("tool" if args.what == "loads" else "direct")
        if not scenes:
            raise NavappError(f"no study scenes in {scene_dir()}: pass --cases")
        if args.quick:
            scenes = scenes[:1]
        elif args.what == "cost":
            scenes = [sc for sc in scenes if sc.stem in ("phantom0-L", "phantom2-R")]
        for sc in scenes:
            folder = args.case_root / sc.stem
            if not (folder / "truth" / "report.json").exists():
                simulate(load_scene(sc), folder)
            cases.append(folder)
    return cases


def cmd_bench(args):
    from .evaluation import benchmark

    if args.what == "precompute":
        benchmark.bench_precompute(args.edges, args.ks, args.volume_ml, args.relax, args.repeats or 1, args.labelmap,
                                   args.phantom)
    elif args.what == "import":
        from .anatomy.importbench import bench_import

        bench_import(args.repeats or 5, args.routes)
    elif args.what == "live":
        from .evaluation.live_bench import bench_live

        bench_live(args.frames, args.planes, args.ks[0], args.edges[0], truth_edge=args.truth_edge)
    else:
        benchmark.bench_register(args.repeats or 5, args.planes, args.ks[0], args.edges[0], truth_edge=args.truth_edge)


def cmd_replay(args):
    from .simulation.scene import demo_scene, load_scene
    from .tracking.replay import run_replay

    scene = load_scene(args.scene) if args.scene else demo_scene()
    latency_ms = args.latency_ms
    if latency_ms is None:  # the scene's declared latency, if any
        latency_ms = next((e.params["ms"] for e in scene.effects if e.kind == "latency"), 0.0)
    names = None
    if args.igtl_config:
        from .tracking.config import load_config

        names = load_config(args.igtl_config)
    out = run_replay(scene, args.port, args.rate, latency_ms / 1000.0, duration_s=args.seconds,
                     out=lambda line: print(line, file=sys.stderr, flush=True), names=names)
    print(json.dumps(out))


class _Parser(argparse.ArgumentParser):
    """argparse, with a bad argument reported in one line (no usage block), exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser():
    p = _Parser(prog="navapp", description="Liver deformation correction (LIBR) from sparse data.")
    p.add_argument("--version", action="version", version=f"navapp {__version__}")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("phantom", help="write the preop/ part of a case folder for a built-in liver phantom")
    s.add_argument("--liver", type=positive(int, least=0), default=0, help="phantom index (0, 1, 2, …; default 0)")
    s.add_argument("--out", type=Path, required=True, help="case folder to write")
    s.set_defaults(func=cmd_phantom)

    s = sub.add_parser("import", help="make a case folder from a patient's surfaces (STL/OBJ/PLY/VTK/VTP) or masks "
                                      "(NIfTI/NRRD/.seg.nrrd/DICOM SEG), e.g. a 3D Slicer or TotalSegmentator export")
    s.add_argument("--out", type=Path, required=True, help="case folder to write")
    structure = "a surface, or a mask (NIfTI/NRRD/DICOM SEG) as FILE or FILE:LABEL (value or segment name)"
    s.add_argument("--liver", action="append", metavar="FILE[:LABEL]", help=f"the liver: {structure}")
    s.add_argument("--portal", action="append", metavar="FILE[:LABEL]", help=f"the portal vein: {structure}")
    s.add_argument("--hepatic", action="append", metavar="FILE[:LABEL]", help=f"the hepatic veins: {structure}")
    s.add_argument("--labelmap", action="append", metavar="FILE|DIR",
                   help="one label map holding several structures, or a folder of one mask per structure "
                        "(TotalSegmentator's output: liver.nii.gz, portal_vein_and_splenic_vein.nii.gz, …)")
    s.add_argument("--labels", help="label values, e.g. liver=1,portal=2,hepatic=3 (default: Slicer segment names)")
    s.add_argument("--frame", type=str.upper, choices=("LPS", "RAS", "LAS"),
                   help="frame of the surface files (3D Slicer exports STL/OBJ in LPS by default)")
    s.add_argument("--falciform", nargs=2, metavar="X,Y,Z",
                   help="two points on the falciform ligament (mm, files' frame)")
    s.add_argument("--regions", type=Path, help="your regions.csv (one label per liver vertex); default: automatic")
    s.add_argument("--portal-centerline", type=Path,
                   help="your portal centerline CSV (x,y,z,branch); default: skeleton")
    s.add_argument("--hepatic-centerline", type=Path, help="your hepatic centerline CSV; default: skeleton")
    s.add_argument("--target", action="append", metavar="FILE[:LABEL]",
                   help="a tumour target: a closed surface, a CSV name,x,y,z[,radius_mm] (files' frame), or a mask "
                        "(one target per piece); repeatable")
    s.add_argument("--overwrite", action="store_true", help="write into a non-empty --out")
    s.set_defaults(func=cmd_import)

    s = sub.add_parser("mesh", help="tetrahedralise a case's liver and print mesh statistics as JSON")
    s.add_argument("case", type=Path, help="case folder")
    s.add_argument("--edge", type=positive(float), default=EDGE_MM,
                   help=f"target element size in mm (default {EDGE_MM:g})")
    s.set_defaults(func=cmd_mesh)

    s = sub.add_parser("precompute", help="mesh a case and compute (or load) its deformation basis")
    s.add_argument("case", type=Path, help="case folder")
    s.add_argument("--edge", type=positive(float), default=EDGE_MM,
                   help=f"target element size in mm (default {EDGE_MM:g})")
    s.add_argument("--k", type=k_count, default=K, help=f"number of control points (default {K})")
    s.set_defaults(func=cmd_precompute)

    from .registration.cli import add_register_parser
    add_register_parser(sub)

    s = sub.add_parser("simulate", help="simulate a scene (navapp/scenes/*.toml) into a case folder")
    s.add_argument("scene", type=Path, help="scene TOML file")
    s.add_argument("--out", type=Path, required=True, help="case folder to write")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("study", help="table2: the paper's Table II design; cost: accuracy against time; "
                                     "robustness: initial offsets × label noise; loads: local tool loads, "
                                     "identity / rigid / LIBR (all resumable)")
    s.add_argument("what", choices=("table2", "cost", "robustness", "error-estimate", "next-plane", "hard", "loads"))
    s.add_argument("--with-cases", type=Path, nargs="+", help="error-estimate, next-plane: a second set of cases "
                   "judged beside --cases (e.g. the laparoscopic ones); error-estimate calibrates on the first "
                   "case's liver in both sets and validates on the other livers")
    s.add_argument("--band-cases", type=Path, nargs="+", help="error-estimate: cases of another kind of deformation "
                   "(e.g. the local loads, tool*) the predicted-error band must hold on too; judged like the others, "
                   "but ê's coefficients (which rank the suggested planes) are not fitted on them")
    s.add_argument("--with-results", type=Path, help="next-plane: the second set's Table II CSV (for the ranks)")
    s.add_argument("--cases", type=Path, nargs="+", help="case folders (default: simulate the nine study scenes)")
    s.add_argument("--case-root", type=Path, default=Path("study-cases"), help="where simulated cases go")
    s.add_argument("--workers", type=positive(int),
                   help="local worker processes (default: all cores for table2, 1 for cost, "
                        "whose timings would compete)")
    s.add_argument("--scheduler", type=address,
                   help="Dask distributed scheduler address (e.g. tcp://host:8786): table2, cost and robustness "
                        "run there")
    s.add_argument("--quick", action="store_true", help="table2: one case, two scenarios per plane level; cost, "
                   "robustness: a smaller design; error-estimate: one plane combination per level and case")
    s.add_argument("--results", type=Path, default=DEFAULT_TABLE2_CSV,
                   help="results CSV, appended (default results/table2.csv; for cost: <report>/cost.csv)")
    s.add_argument("--report", type=Path, default=Path("results"), help="folder for table2.md and plots")
    s.add_argument("--edge", type=positive(float), default=EDGE_MM,
                   help=f"registration mesh element size, mm (default {EDGE_MM:g}; not cost, which sweeps it; "
                        "12 with --k 12 for a quick look)")
    s.add_argument("--k", type=k_count, default=K,
                   help=f"number of control points (default {K}; not cost, which sweeps it)")
    s.set_defaults(func=cmd_study)

    s = sub.add_parser("bench", help="benchmarks that print timings and memory as JSON lines")
    s.add_argument("what", choices=("precompute", "register", "live", "import"))
    s.add_argument("--edges", type=positive(float), nargs="+", default=[EDGE_MM], help="element sizes, mm")
    s.add_argument("--ks", type=k_count, nargs="+", default=[K], help="numbers of control points")
    s.add_argument("--volume-ml", type=positive(float), help="precompute: the phantom scaled to this volume, ml")
    s.add_argument("--relax", choices=("local", "exact", "both"), default="local",
                   help="precompute: relaxation subdomain (both: exact and local, with the local one's error)")
    s.add_argument("--phantom", type=int, choices=range(4), default=0,
                   help="precompute: which phantom's liver (default 0)")
    s.add_argument("--labelmap", action="store_true",
                   help="precompute: the liver as navapp's import of its CT label map gives it (a voxel staircase, "
                        "as a real segmentation's), not the phantom's smooth surface")
    s.add_argument("--repeats", type=positive(int),
                   help="register, import: repetitions for the median (default 5); precompute: before/after pairs "
                        "of fresh-process runs, alternated (default 1)")
    s.add_argument("--planes", type=positive(int), default=3, help="register: iUS planes (≥ 2); live: planes kept")
    s.add_argument("--routes", nargs="+", choices=("nifti masks", "nrrd label map", "dicom seg",
                                                   "totalsegmentator folder", "stl"), metavar="ROUTE",
                   help="import: only these routes (quoted names: 'nifti masks', 'nrrd label map', 'dicom seg', "
                        "'totalsegmentator folder', 'stl'; the STL route alone skips the CT grid); default all")
    s.add_argument("--frames", type=positive(int), default=40, help="live: ultrasound frames re-registered")
    s.add_argument("--truth-edge", type=positive(float),
                   help="register, live: element size of the mesh the demo scene's truth is simulated on, mm "
                        "(default: the scene's, 3.5; 12 with --edges 12 --ks 12 for a quick look)")
    s.set_defaults(func=cmd_bench)

    s = sub.add_parser("replay", help="OpenIGTLink server playing a simulated scene as PLUS would (stylus, probe, "
                                      "B-mode frames): the demo without hardware")
    s.add_argument("scene", type=Path, nargs="?", help="scene TOML file (default: the built-in demo scene)")
    s.add_argument("--port", type=_port, default=18944, help="port on 127.0.0.1 (default 18944)")
    s.add_argument("--rate", type=positive(float), default=25.0, help="messages per second per device (default 25)")
    s.add_argument("--latency-ms", type=positive(float, least=0), default=None,
                   help="send each message this long after its timestamp (default: the scene's declared latency, or 0)")
    s.add_argument("--seconds", type=positive(float), help="stop after this long (default: until Ctrl-C)")
    s.add_argument("--igtl-config", type=Path, metavar="FILE",
                   help="tracking TOML naming the devices sent, as the viewer's; a [tools.<source>] table sends "
                        "that source's points in its tool's frame with its pose (default: PLUS's names, points in "
                        "Reference)")
    s.set_defaults(func=cmd_replay)

    s = sub.add_parser("demo",
                       help="simulate the built-in demo scene (phantom 0, stylus, 16 iUS planes) and register it")
    s.add_argument("--out", type=Path, default=Path("navapp-demo"), help="case folder to write (default ./navapp-demo)")
    s.add_argument("--truth-edge", type=positive(float),
                   help="element size of the mesh the truth is simulated on, mm (default: the scene's, 3.5)")
    s.add_argument("--edge", type=positive(float), default=EDGE_MM,
                   help=f"registration mesh element size, mm (default {EDGE_MM:g})")
    s.add_argument("--k", type=k_count, default=K, help=f"number of control points (default {K})")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("serve", help="open the navigation viewer in the browser (built-in demo scene by default)")
    s.add_argument("scene", type=Path, nargs="?", help="scene TOML file (default: the built-in demo scene)")
    s.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    s.add_argument("--port", type=_port, default=8080,
                   help="port (default 8080; if busy the next free one is used and printed)")
    s.add_argument("--session", type=Path,
                   help="session folder (default ~/navapp-sessions/<scene>-<key>, or under $NAVAPP_SESSIONS)")
    s.add_argument("--edge", type=positive(float), default=EDGE_MM, help="registration mesh element size, mm")
    s.add_argument("--k", type=k_count, default=K, help="number of control points")
    s.add_argument("--view2d-port", type=positive(int, most=65535, least=0), default=None,
                   help="port of the 2D ultrasound view's pages (default: the viewer's port + 1 where free, "
                        "else any free port; 0: any free port)")
    s.add_argument("--igtl", metavar="HOST:PORT",
                   help="connect to an OpenIGTLink server (PLUS, 3D Slicer, navapp replay) for the tracked "
                        "stylus and ultrasound")
    s.add_argument("--slicer", metavar="[HOST:]PORT",
                   help="send registrations to 3D Slicer over OpenIGTLink: HOST:PORT connects to Slicer's "
                        "OpenIGTLinkIF connector in server mode; PORT alone listens for it in client mode")
    s.add_argument("--igtl-config", type=Path, metavar="FILE",
                   help="tracking TOML (PLUS transform names, ImageToProbe, timeouts); see README, 'With a tracker'")
    s.add_argument("--token", help="the token the viewer's link must carry (default $NAVAPP_TOKEN; when --host is not "
                                   "a loopback address and neither is given, a random one, printed in the URL)")
    s.add_argument("--certfile", type=Path, help="TLS certificate (PEM) for https and wss")
    s.add_argument("--keyfile", type=Path, help="its private key (PEM; default: in --certfile)")
    s.set_defaults(func=cmd_serve)

    return p


def _output_lock(args):
    """The lock on the folder a command writes (``navapp.outputs``): two runs writing one
    folder at once mixed their files; the second now stops at once, in one line."""
    from contextlib import ExitStack, nullcontext

    from .outputs import folder_lock

    if args.command == "register":
        return folder_lock(args.out or Path(args.case) / "registration")
    if args.command in ("demo", "simulate"):
        return folder_lock(args.out)
    if args.command == "study":
        # two runs of a study appending to one CSV both skipped the same cases, wrote them
        # twice, and the report averaged the doubled rows without a word (seen: the loads
        # study's identity mean 7.81 read as 8.66)
        stack = ExitStack()
        try:
            stack.enter_context(folder_lock(Path(args.report) / args.what, kind="study report"))
            if args.what in APPENDING_STUDIES:
                stack.enter_context(folder_lock(_study_results(args), kind="results file"))
        except BaseException:
            stack.close()
            raise
        return stack
    return nullcontext()


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    progress.QUIET = args.quiet
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.simplefilter("ignore", CarriedWarning)  # printed once, with the case, from the registration's own
        warnings.showwarning = lambda msg, *a, **k: progress.echo(f"navapp: warning: {msg}")
        try:
            with _output_lock(args):
                return args.func(args) or 0
        except NavappError as exc:
            print(f"navapp: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("navapp: interrupted", file=sys.stderr)
            return 130
        except MemoryError:
            print("navapp: error: out of memory (try a coarser --edge or smaller --k)", file=sys.stderr)
            return 2


if __name__ == "__main__":
    sys.exit(main())
