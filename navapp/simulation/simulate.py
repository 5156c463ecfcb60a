"""Run a scene: ground truth, stylus data, iUS planes and images, effects → a case folder.

Writes, besides the standard case folder (docs/design.md §3) whose ``intraop/`` holds the
stylus data plus every plane's features (the "S + all planes" level):
- ``intraop/us/planes.json``: per plane its index, orientation, true ProbeToTracker
  pose, the probe calibration (ImageToProbe) and its feature files;
- ``intraop/us/plane_XX/<feature>.csv`` and ``intraop/us/plane_XX.png`` (the B-mode image);
- ``truth/liver.ply``, ``truth/portal.ply``, ``truth/hepatic.ply`` and the deformed
  centerlines: the true intraoperative anatomy, used for the CBCT and iCT data levels;
- ``truth/field.npz``: the ground truth as a field (``anatomy.truth.TruthField``: the truth
  mesh, its nodal displacement, the tracker offset), which evaluation asks at whatever
  points it evaluates — no registration mesh is built here;
- ``truth/targets/``: the tumour targets deformed by the ground truth (their TRE);
- ``truth/report.json``: displacement statistics, coverage, points per plane, seconds and
  the ledger of stages and effects that ran.
"""

import json
import time
from pathlib import Path

import numpy as np
import trimesh

from .. import progress
from ..anatomy.caseio import Case, read_case, write_case, write_csv
from ..anatomy.meshing import cached_tetmesh, check_size
from ..anatomy.model import PreopModel
from ..anatomy.phantom import make_phantom
from ..anatomy.targets import TARGETS_DIR, map_targets, write_targets
from ..anatomy.truth import TruthField
from ..errors import InputError
from ..mechanics.fem import NU_LIVER, Material
from ..outputs import folder_lock, staged
from . import effects as fx
from .scene import Scene
from .sources import Sight, registered
from .sources.ius import write_frames
from .tool import place_tool
from .transpose import correspondence, reference_deformation, transpose
from .truth import Loading, Supports, solve_linear, solve_neo_hookean, supported_nodes


def gravity_direction(release: str, tilt_deg: float, head_up_deg: float = 0.0) -> tuple:
    """Posterior gravity tilted toward the released side (L: +x, R: −x, N: inferior), then
    by ``head_up_deg`` toward inferior (reverse Trendelenburg, the usual position for
    upper-abdominal laparoscopy). Unit vector."""
    t = np.radians(tilt_deg)
    side = {"L": np.array([1.0, 0.0, 0.0]), "R": np.array([-1.0, 0.0, 0.0]), "N": np.array([0.0, 0.0, -1.0])}[release]
    g = np.cos(t) * np.array([0.0, -1.0, 0.0]) + np.sin(t) * side
    if head_up_deg:
        h = np.radians(head_up_deg)
        g = np.cos(h) * g + np.sin(h) * np.array([0.0, 0.0, -1.0])
        g = g / np.linalg.norm(g)
    return tuple(g)


def scene_preop(scene: Scene):
    """The preoperative anatomy ``scene`` is simulated on (``PreopModel``): its phantom, or
    its case folder's ``preop``."""
    return make_phantom(scene.phantom) if scene.phantom is not None else read_case(scene.case).preop


def simulate(scene: Scene, out: Path, cache_root=None) -> dict:
    """Simulate ``scene`` into case folder ``out``; returns the report (``truth/report.json``).
    The truth is written as a field on the truth mesh (``scene.mesh_edge_mm``), apart from
    any registration mesh."""
    _check_out(scene, Path(out))
    t0 = time.perf_counter()
    ledger = fx.Ledger()
    rng = np.random.default_rng(scene.seed)
    preop = scene_preop(scene)
    if preop.regions is None:

        raise InputError("the scene's anatomy needs preop/regions.csv (anterior surface for the stylus and probe)")
    reference = make_phantom(scene.transpose_from.phantom) if scene.transpose_from is not None else None
    check_scene_size(scene, preop, reference)
    truth_mesh, _ = cached_tetmesh(preop.liver, scene.mesh_edge_mm, cache_root)
    loading, material = scene_loading(scene, truth_mesh)
    if loading.tool is not None:
        ledger.mark("tool")
    transposed = None
    if scene.transpose_from is not None:
        u, transposed = transposed_truth(scene, preop, truth_mesh, ledger, cache_root, reference)
    else:
        if scene.large:
            ledger.mark("nonlinear_solve")
            u = newton_with_progress("ground truth (neo-Hookean, Newton)", truth_mesh, loading, material)
        else:
            with progress.stage("ground truth (linear)"):
                ledger.mark("linear_solve")
                u = solve_linear(truth_mesh, loading, material)
    t_truth = time.perf_counter() - t0

    eff = {e.kind: e.params for e in scene.effects}
    offset = np.eye(4)
    if "tracker_offset" in eff:
        # its own stream: declaring it leaves every other draw of the scene as it was
        offset = fx.tracker_offset(preop.liver.vertices.mean(0), np.random.default_rng([scene.seed, 7]), ledger,
                                   **eff["tracker_offset"])

    truth = TruthField(truth_mesh.nodes, truth_mesh.tets, u, offset)
    moved = truth.at  # where a preoperative point is, in tracker space

    liver_d = trimesh.Trimesh(moved(preop.liver.vertices), preop.liver.faces, process=False)
    portal_d, hepatic_d = (None if m is None else trimesh.Trimesh(moved(m.vertices), m.faces, process=False)
                           for m in (preop.portal, preop.hepatic))

    # the data sources (``sources``): those in every scene (the stylus, then the iUS planes) on
    # the scene's own stream, in the order they always drew; each other source the scene enables
    # on its own stream, so that enabling one leaves every other draw of the scene as it was
    intraop: dict = {}
    sourced: dict = {}
    frames: list = []
    always = [n for n in scene.sources if registered()[n].always]
    others = sorted(n for n in scene.sources if n not in always)
    streams = [(n, rng) for n in always] + [(n, np.random.default_rng([scene.seed, 11, i]))
                                             for i, n in enumerate(others)]
    vessels = {k: m for k, m in (("portal", portal_d), ("hepatic", hepatic_d)) if m is not None}
    sight = Sight(liver_d, preop, ledger, vessels, tuple(scene.effects), scene.seed)
    for name, srng in streams:
        source = registered()[name]
        got = source.acquire(scene.sources[name], sight, srng)
        frames += got.frames
        kept = {}
        for label, pts in got.points.items():
            if not source.acquires_effects and "tracking_noise" in eff and len(pts):
                pts = fx.tracking_noise(pts, srng, ledger, **eff["tracking_noise"])
            if not source.acquires_effects and "dropout" in eff and len(pts):
                pts = fx.dropout(pts, srng, ledger, **eff["dropout"])
            kept[label] = int(len(pts))
            if len(pts):
                intraop[label] = np.vstack([intraop[label], pts]) if label in intraop else pts
        if source.acquires_effects:  # its report is whole (the planes': points per plane)
            pass
        elif name in always:  # the stylus's entry reads as it always has: points of the features that have any
            got.report["points"] = {k: n for k, n in kept.items() if n}
        else:
            got.report["kept"] = kept
        sourced[source.report_as] = got.report
    _check_data(scene, intraop)

    # absolute: the case is read later from anywhere (a study's ``declared_supports`` reads the scene again)
    settings: dict = {"name": scene.name, "units": "mm",
                      "scene": str(Path(scene.source).resolve()) if scene.source else scene.name}
    if (pose := scene.declared_pose()) is not None:
        settings["intraop"] = {"pose": {"known": True, "sd_mm": float(pose[0]), "sd_deg": float(pose[1])}}
    case = Case(preop=preop, intraop=intraop, truth=truth, settings=settings)
    # the whole case is written aside and moved into place: simulating into a folder that held
    # another case (16 planes, then none) left the old planes' contours and images beside the new
    # report, and register would have used them; a run stopped half way leaves the old case whole
    with folder_lock(out), staged(out) as folder:
        write_case(case, folder)
        write_frames(folder, frames)
        tdir = Path(folder) / "truth"
        liver_d.export(tdir / "liver.ply", encoding="binary")
        for name, mesh in (("portal", portal_d), ("hepatic", hepatic_d)):
            if mesh is not None:
                mesh.export(tdir / f"{name}.ply", encoding="binary")
            cl = preop.centerline(name)
            if cl is not None:
                write_csv(tdir / f"{name}_centerline.csv", np.column_stack([moved(cl.points), cl.branch]),
                          ("x", "y", "z", "branch"), True)
        if preop.targets:
            write_targets(map_targets(preop.targets, moved), tdir / TARGETS_DIR)
        d = np.linalg.norm(u, axis=1)  # at the truth mesh's nodes
        report = {
            "scene": scene.name, "truth_nodes": int(len(truth_mesh.nodes)),
            "displacement_mm": {"mean": round(float(d.mean()), 2), "max": round(float(d.max()), 2)},
            # the stylus's entry and the planes' where they always were
            **{k: sourced.pop(k) for k in [registered()[n].report_as for n in always]},
            "seconds": {"truth": round(t_truth, 2), "total": round(time.perf_counter() - t0, 2)},
            "ran": sorted(set(ledger.ran)),
        }
        report.update(sourced)
        if transposed is not None:
            report["transposed"] = transposed
        if loading.tool is not None:
            tool = loading.tool
            c = np.asarray(tool.centre)[None]
            report["tool"] = {"centre_mm": np.round(tool.centre, 2).tolist(),
                              "push": np.round(tool.direction, 4).tolist(), "radius_mm": tool.radius_mm,
                              "load": str(tool.load),
                              "depth_mm": round(float(truth.displacement(c)[0] @ np.asarray(tool.direction)), 2)}
        if "tracker_offset" in eff:
            report["tracker_offset"] = offset.round(6).tolist()
        (tdir / "report.json").write_text(json.dumps(report, indent=1))
    return report


def _check_out(scene: Scene, out: Path):
    """``out`` is replaced whole by the new case: refuse, before any work, a folder that holds
    something other than a case, and the patient case the scene takes its anatomy from."""
    if scene.case is not None and out.exists() and Path(scene.case).resolve() == out.resolve():
        raise InputError("is the case this scene takes its anatomy from; simulate into another folder", out)
    if out.is_dir() and any(out.iterdir()) and not (out / "case.toml").exists():
        raise InputError("holds files and is not a case folder; simulate into a new folder or a case folder "
                         "(which the new case replaces)", out)


def check_scene_size(scene: Scene, preop: PreopModel, reference: PreopModel | None = None):
    """Refuse, before any work, a scene whose truth mesh (``deformation.mesh_edge_mm`` on its
    liver; ``transpose_from.mesh_edge_mm`` on the ``reference`` phantom) would not fit in
    memory, in one line naming the scene file and the key to change. A tiny edge got as far
    as the mesher's own check, whose line named neither and advised a --edge that
    ``simulate`` does not have."""
    where = scene.source or scene.name
    check_size(preop.liver, scene.mesh_edge_mm, "deformation.mesh_edge_mm", where)
    if reference is not None and scene.transpose_from is not None:
        check_size(reference.liver, scene.transpose_from.mesh_edge_mm, "deformation.transpose_from.mesh_edge_mm",
                   where)


MIN_DATA_POINTS = 6
"""The fewest intraoperative points a simulated case may have: fewer cannot fix a rigid pose
(``registration.pipeline.MIN_SURFACE_POINTS``). A scene whose effects leave fewer (a dropout
fraction of 0.99999 kept none) wrote a case without intraop data and exited 0."""


def _check_data(scene: Scene, intraop: dict):
    """Refuse, in one line naming the scene file, a scene that leaves (almost) no data."""
    n = sum(len(p) for p in intraop.values())
    if n >= MIN_DATA_POINTS:
        return
    drop = next((e.params["fraction"] for e in scene.effects if e.kind == "dropout"), None)
    cause = f" after a dropout of {drop:g}" if drop else ""
    fix = "lower the dropout fraction" if drop else "add data (stylus.coverage, stylus.points, ius.planes)"
    raise InputError(f"the scene leaves {n} intraoperative data point{'s' if n != 1 else ''}{cause}: a case needs "
                     f"at least {MIN_DATA_POINTS} to register; {fix}", scene.source or scene.name)


def newton_with_progress(desc, mesh, loading, material, **kw):
    """``solve_neo_hookean`` behind a bar of the way done (the load applied, or with a pressure
    tool the fraction of its depth reached), elapsed time and an estimate of the rest, from
    the rate so far: rough, as increments are cut where the organ softens and the last
    stretch to the depth is a search, but a solve of many minutes is no longer a bare clock."""
    with progress.work(desc, 1000) as bar:
        return solve_neo_hookean(mesh, loading, material, reached=lambda t: bar.to(round(1000 * t)), **kw)


def scene_loading(scene: Scene, mesh=None) -> tuple[Loading, Material]:
    """The truth's loads and material as the scene declares them; a ``[tool]`` is placed on
    ``mesh`` (the truth's own)."""
    tool = None
    if scene.tool is not None:
        if mesh is None:
            raise ValueError("a scene with a tool needs the truth mesh to place it")
        tool = place_tool(mesh, scene.tool)
    loading = Loading(gravity=9.81 if scene.gravity else 0.0,
                      gravity_dir=gravity_direction(scene.release, scene.gravity_tilt_deg, scene.head_up_deg),
                      pressure=scene.pressure_pa, release=scene.release, supports=Supports(scene.supports), tool=tool)
    return loading, Material(E=scene.truth_E_pa, nu=NU_LIVER)


def transposed_truth(scene: Scene, preop, truth_mesh, ledger=None, cache_root=None,
                     reference: PreopModel | None = None) -> tuple[np.ndarray, dict]:
    """The scene's loads deform the reference phantom (``deformation.transpose_from``; built
    here unless given as ``reference``); its displacement is carried onto the nodes of
    ``truth_mesh`` (this liver's) through an inexact correspondence (``transpose.py``).
    Returns the nodal displacements (M, 3) mm and what the report says about them."""

    ledger = ledger or fx.Ledger()
    loading, material = scene_loading(scene)
    src = scene.transpose_from
    if src is None:
        raise ValueError(f"scene {scene.name!r} declares no deformation.transpose_from")
    ref = make_phantom(src.phantom) if reference is None else reference
    with progress.stage(f"reference liver (phantom {src.phantom}) under laparoscopic loading"
                        + (" (neo-Hookean, Newton)" if scene.large else " (linear)")):
        ledger.mark("nonlinear_solve" if scene.large else "linear_solve")
        ref_mesh, u_ref = reference_deformation(ref.liver, src.mesh_edge_mm, loading, material, scene.large, cache_root)
    with progress.stage("correspondence (affine + deformable CPD, thin-plate spline) and transposition"):
        ledger.mark("transposition")
        phi = correspondence(preop.liver.vertices, ref.liver.vertices, seed=scene.seed)
        u = transpose(ref_mesh, u_ref, phi, truth_mesh.nodes)
    held = np.unique(np.concatenate(list(supported_nodes(truth_mesh, scene.release).values())))

    def stats(u):
        d = np.linalg.norm(u, axis=1)
        return {"mean": round(float(d.mean()), 2), "max": round(float(d.max()), 2)}

    return u, {"reference_phantom": src.phantom, "reference_nodes": int(len(ref_mesh.nodes)),
               "reference_displacement_mm": stats(u_ref), "correspondence_residual_mm": round(phi.residual_mm, 2),
               # the target's own supports are not re-clamped (transpose.py): how far they move
               "support_displacement_mm": stats(u[held])}
