"""``navapp bench import``: the import of a CT-sized patient, route by route.

Phantom 0's liver and both vessel trees are voxelised on a 512 × 512 × 200 CT grid
(0.7 × 0.7 × 2.5 mm, oblique: ``ctcase``) and written as three NIfTI masks, one NRRD label
map, one DICOM SEG, a TotalSegmentator-style folder and three STL surfaces. Each route is
imported by ``navapp import`` in a child process of its own, so that its peak memory is its
own (the child's maximum resident set, from ``wait4``; the parent stays small, as Linux
counts the parent's resident set at the fork); the child's JSON gives the stage times. One
JSON line per route.
"""

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROUTES = ("nifti masks", "nrrd label map", "dicom seg", "totalsegmentator folder", "stl")
"""The import routes, in the order ``bench import`` runs them."""


def write_routes(folder: Path, routes: list[str] | None = None) -> dict[str, list[str]]:
    """The phantom written every way (or only for ``routes``: the STL route alone skips the
    CT grid); route name → ``navapp import`` arguments."""
    from . import ctcase
    from .phantom import make_phantom

    model = make_phantom(0)
    stl = {"stl": ["--liver", str(folder / "liver.stl"), "--portal", str(folder / "portal.stl"),
                   "--hepatic", str(folder / "hepatic.stl")]}
    for s in ctcase.STRUCTURES:
        ctcase.write_stl(getattr(model, s), folder / f"{s}.stl")
    if routes is not None and set(routes) <= {"stl"}:
        return stl
    vc = ctcase.ct_case(model)
    names = dict(enumerate(ctcase.STRUCTURES, start=1))  # the label values ``ct_case`` writes
    masks = folder / "masks"
    masks.mkdir()
    for s, m in vc.masks.items():
        ctcase.write_nifti(m, vc.affine, masks / f"{s}.nii.gz")
    ts = folder / "totalsegmentator"
    ts.mkdir()
    ctcase.write_nifti(vc.masks["liver"], vc.affine, ts / "liver.nii.gz")
    ctcase.write_nifti(vc.masks["portal"], vc.affine, ts / "portal_vein_and_splenic_vein.nii.gz")
    labels = vc.labels()
    ctcase.write_nrrd(labels, vc.affine, folder / "segmentation.seg.nrrd", names)
    ctcase.write_dicom_seg(labels, vc.affine, folder / "seg.dcm", names)
    return {
        "nifti masks": ["--liver", str(masks / "liver.nii.gz"), "--portal", str(masks / "portal.nii.gz"),
                        "--hepatic", str(masks / "hepatic.nii.gz")],
        "nrrd label map": ["--labelmap", str(folder / "segmentation.seg.nrrd")],
        "dicom seg": ["--labelmap", str(folder / "seg.dcm")],
        "totalsegmentator folder": ["--labelmap", str(ts)],
        **stl,
    }


def run_import(args: list[str], out: Path) -> dict:
    """One ``navapp import`` in a child process: wall seconds, the child's peak MB (its own
    maximum resident set, from ``wait4``), the stage seconds it reports."""
    cmd = [sys.executable, "-m", "navapp", "--quiet", "import", *args, "--out", str(out), "--overwrite"]
    with tempfile.TemporaryFile("w+") as so, tempfile.TemporaryFile("w+") as se:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=so, stderr=se, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        so.seek(0)
        se.seek(0)
        stdout, stderr = so.read(), se.read()
    if proc.returncode != 0:
        raise RuntimeError(f"navapp import {' '.join(args)} failed ({proc.returncode}): "
                           f"{(stderr.strip().splitlines() or [''])[-1]}")
    report = json.loads(stdout.strip().splitlines()[-1])
    return {"wall_s": round(wall, 2), "peak_mb": round(usage.ru_maxrss / 1024.0, 1),
            "stages_s": report.get("seconds", {})}


def bench_import(repeats: int = 1, routes: list[str] | None = None):
    """One JSON line for the writing, then one per route (``routes``: some of ``ROUTES``; None: all)."""
    with tempfile.TemporaryDirectory(prefix="navapp-bench-import-") as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        # written by a child: a process's peak memory counts its parent's at the fork
        # (Linux keeps the larger), so this process stays small for the imports' children
        code = ("import json, sys; from pathlib import Path; from navapp.anatomy.importbench import write_routes; "
                "print(json.dumps(write_routes(Path(sys.argv[1]), json.loads(sys.argv[2]))))")
        res = subprocess.run([sys.executable, "-c", code, str(folder), json.dumps(routes)], capture_output=True,
                             text=True, check=True)
        all_routes = json.loads(res.stdout.strip().splitlines()[-1])
        grid = not (routes and set(routes) <= {"stl"})
        print(json.dumps({"bench": "import", "case": "phantom 0 on a 512x512x200 CT grid, 0.7x0.7x2.5 mm, oblique"
                          if grid else "phantom 0's surfaces as STL (no CT grid written)",
                          "write_s": round(time.perf_counter() - t0, 1)}), flush=True)
        for route, args in all_routes.items():
            if routes and route not in routes:
                continue
            runs = [run_import(args, folder / "case") for _ in range(repeats)]
            walls = [r["wall_s"] for r in runs]
            print(json.dumps({"route": route, "wall_s_median": round(statistics.median(walls), 2), "wall_s": walls,
                              "peak_mb_max": max(r["peak_mb"] for r in runs), "stages_s": runs[-1]["stages_s"]}),
                  flush=True)
