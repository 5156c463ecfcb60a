"""Tetrahedral meshing of the liver surface: Gmsh first, fTetWild when Gmsh cannot (the
calls themselves: ``mesh_engines``).

Gmsh (GPL-2.0-or-later, pip wheel) re-parametrises and remeshes the input surface at the
requested edge length before filling the volume, so tet quality does not depend on the
triangles the user supplied; re-parametrisation can fail or hang on sharp or unevenly
triangulated surfaces, so every attempt runs in a child process under a CPU work budget
(the same on a busy machine as on a quiet one, so the mesh never depends on the load) and
fTetWild (pytetwild wheel), which needs no parametrisation, is the last resort. Every
mesh returned meets the quality floor: no inverted tet, no dihedral angle under 5°.
"""

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import trimesh

from ..budget import NODES_PER_EDGE3 as _NODES_PER_EDGE3
from ..defaults import EDGE_MM
from ..errors import NavappError
from ..switches import Before
from .manifold import boundary_defects, mend_pinches
from .tets import TetMesh, tet_volumes  # TetMesh re-exported: its home is tets.py


def dihedral_angles(nodes, tets):
    """(E, 6) interior dihedral angles in degrees."""
    p = nodes[tets]
    faces = [(1, 2, 3, 0), (0, 3, 2, 1), (0, 1, 3, 2), (0, 2, 1, 3)]
    normals = []
    for i, j, k, _ in faces:
        n = np.cross(p[:, j] - p[:, i], p[:, k] - p[:, i])
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
    out = []
    for a in range(4):
        for b in range(a + 1, 4):
            c = np.einsum("ij,ij->i", normals[a], normals[b])
            out.append(180.0 - np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.column_stack(out)


def radius_ratio(nodes, tets):
    """Normalised radius ratio 3 r_in / r_circ in (0, 1]; 1 for the regular tet."""
    p = nodes[tets]
    vol = np.abs(tet_volumes(nodes, tets))
    areas = 0.0
    for i, j, k in [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]:
        areas = areas + 0.5 * np.linalg.norm(np.cross(p[:, j] - p[:, i], p[:, k] - p[:, i]), axis=1)
    r_in = 3 * vol / areas
    a = p[:, 1] - p[:, 0]
    b = p[:, 2] - p[:, 0]
    c = p[:, 3] - p[:, 0]
    num = (np.einsum("ij,ij->i", a, a)[:, None] * np.cross(b, c) + np.einsum("ij,ij->i", b, b)[:, None] * np.cross(c, a)
           + np.einsum("ij,ij->i", c, c)[:, None] * np.cross(a, b))
    r_circ = np.linalg.norm(num, axis=1) / (12 * vol)
    return 3 * r_in / r_circ


def quality_report(mesh: TetMesh) -> dict:
    """Node/element counts and quality figures of a tet mesh."""
    vol = tet_volumes(mesh.nodes, mesh.tets)
    dih = dihedral_angles(mesh.nodes, mesh.tets)
    rr = radius_ratio(mesh.nodes, mesh.tets)
    edges = np.concatenate([mesh.nodes[mesh.tets[:, i]] - mesh.nodes[mesh.tets[:, j]]
                            for i in range(4) for j in range(i + 1, 4)])
    return {
        "nodes": int(len(mesh.nodes)),
        "elements": int(len(mesh.tets)),
        "surface_nodes": int(len(mesh.surface_nodes())),
        "inverted": int((vol <= 0).sum()),
        "min_dihedral_deg": float(dih.min()),
        "max_dihedral_deg": float(dih.max()),
        "tets_below_5deg": int((dih.min(1) < 5).sum()),
        "min_radius_ratio": float(rr.min()),
        "mean_radius_ratio": float(rr.mean()),
        "mean_edge_mm": float(np.linalg.norm(edges, axis=1).mean()),
        "volume_mm3": float(vol.sum()),
    }


@dataclass(frozen=True)
class MeshAttempt:
    """One way of meshing: ``method`` "gmsh" (remesh the surface on re-parametrised patches
    split at ``feature_angle`` degrees, then fill the volume: ``volume`` "delaunay", 3D
    Delaunay + Gmsh's and Netgen's optimisers, or "hxt", HXT + Gmsh's optimiser alone) or
    "ftetwild" (envelope-based: never needs a parametrisation); ``limit`` CPU seconds at most."""

    method: str
    feature_angle: float = 40.0
    limit: float | None = None  # CPU s; None: scaled to the expected mesh (``work_budget``)
    edge_scale: float = 1.0  # the attempt meshes at edge × edge_scale
    volume: str = "delaunay"  # Gmsh's volume stage (``mesh_engines.VOLUME_MESHERS``)


ATTEMPTS = (
    MeshAttempt("gmsh", 40.0),
    MeshAttempt("gmsh", 60.0),
    MeshAttempt("gmsh", 90.0),
    MeshAttempt("ftetwild"),
    MeshAttempt("ftetwild", edge_scale=0.85),
)
"""Tried in order until one passes the quality floor, less the Gmsh angles whose failure the
surface tells in advance (``plan_mesh``, ``feature_spacing``). Gmsh at 40° gives the meshes navapp
was measured with; larger angles make fewer, larger patches, which is what lets
re-parametrisation succeed on sharp or unevenly triangulated surfaces; fTetWild is the
fallback that cannot fail on a valid closed surface, tried a second time on a slightly
finer edge because its boundary can come out pinched beyond mending (choices and timings:
docs/decisions/anatomy.md, "Meshing any liver" and "Pinched boundaries")."""

MESHERS = ("auto", "gmsh", "ftetwild")
"""``$NAVAPP_MESHER``: "auto" (the chain above), or only the attempts of one method."""

NODES_PER_EDGE3 = _NODES_PER_EDGE3
"""Expected nodes = volume / (1.24 edge³): fitted on the phantoms (Gmsh; fTetWild's edge is
scaled by ``mesh_engines.FTETWILD_EDGE_FACTOR`` to give the same count)."""

CPU_SECONDS = {"gmsh": (6.0, 0.0006), "ftetwild": (15.0, 0.0035)}
"""Expected CPU seconds of one attempt, a + b × expected nodes (interpreter start-up and
imports included; measured, docs/decisions/house.md, "Same answer on a busy machine")."""

WORK_FACTOR = 4.0
"""An attempt may use this many times its expected CPU seconds. CPU time, unlike wall
time, does not grow when the machine is busy, so whether an attempt is stopped depends on
the surface, not on the load; a Gmsh hang (a property of the surface) ends there."""


def expected_nodes(surface: trimesh.Trimesh, edge: float) -> int:
    """Nodes a mesh of ``surface`` at ``edge`` mm will have, from its volume (up front)."""
    return int(round(abs(float(surface.volume)) / (NODES_PER_EDGE3 * edge ** 3)))


def check_size(surface: trimesh.Trimesh, edge: float, setting: str = "--edge", path=None):
    """Refuse, before any work, a mesh of ``surface`` at ``edge`` mm beyond the memory budget
    (``budget.check_mesh``), in one line naming ``path`` (e.g. the scene file) and what to
    change (``setting``: "--edge", or the scene key that set the edge)."""
    from .. import budget

    budget.check_mesh(expected_nodes(surface, edge), edge, abs(float(surface.volume)), setting, path)


def expected_cpu(attempt: MeshAttempt, nodes: int) -> float:
    """Expected CPU seconds of ``attempt`` for a mesh of ``nodes`` nodes."""
    a, b = CPU_SECONDS[attempt.method]
    return a + b * nodes / attempt.edge_scale ** 3


def work_budget(attempt: MeshAttempt, nodes: int) -> float:
    """CPU seconds ``attempt`` may use: its own ``limit``, else ``WORK_FACTOR`` × expected."""
    return attempt.limit if attempt.limit is not None else WORK_FACTOR * expected_cpu(attempt, nodes)


MIN_DIHEDRAL_DEG = 5.0  # the quality floor: no tet with a dihedral angle below this


def time_limit() -> float | None:
    """The meshing wall-clock limit in seconds (``$NAVAPP_MESH_TIMEOUT``), or None: by
    default meshing has none, each attempt being bounded by its CPU work budget; a wall-clock
    limit, when set, only ever stops meshing with an error."""
    value = os.environ.get("NAVAPP_MESH_TIMEOUT")
    if not value:
        return None
    try:
        seconds = float(value)
    except ValueError:
        raise NavappError(f"NAVAPP_MESH_TIMEOUT={value!r} is not a number of seconds") from None
    if not seconds > 0:
        raise NavappError(f"NAVAPP_MESH_TIMEOUT={value!r} must be a positive number of seconds")
    return seconds


def mesher_choice() -> str:
    """``$NAVAPP_MESHER`` (default "auto"), checked against ``MESHERS``."""
    choice = os.environ.get("NAVAPP_MESHER", "auto").strip().lower() or "auto"
    if choice not in MESHERS:
        raise NavappError(f"NAVAPP_MESHER={choice!r}: expected one of {', '.join(MESHERS)}")
    return choice


FEATURE_SPACING_MIN = 10.0
"""A Gmsh attempt is skipped when the surface's feature lines at its angle (edges between
triangles whose normals differ by more than the angle) lie on average closer together than
this many mesh edges (``feature_spacing``): Gmsh keeps every feature line as a patch
boundary and meshes the strips between them, which at a spacing of a few edges ends in
"Wrong topology of boundary mesh for parametrization" or in slivers under the quality floor.
Measured (docs/decisions/speed.md, "Choosing Gmsh's feature angle from the surface"): livers
imported from CT label maps failed at 1.4–9.1 edges and meshed at 13 and more; the
phantoms have no feature line at 40°, the test surfaces from other generators 12–27 edges."""


def feature_spacing(surface: trimesh.Trimesh, angle: float, edge: float) -> float:
    """Mean spacing of ``surface``'s feature lines at ``angle`` degrees, in edges of
    ``edge`` mm: its area over the feature lines' length, over ``edge`` (inf: none).

    A feature line is an edge whose two triangles' normals differ by more than ``angle``
    (what Gmsh's ``classifySurfaces`` splits patches at). A voxel staircase left by
    marching cubes, smoothing and decimation of a CT label map has thousands of them at 40°.
    """
    adjacency = surface.face_adjacency_edges
    crease = np.degrees(surface.face_adjacency_angles) > angle
    if not crease.any():
        return float("inf")
    v = np.asarray(surface.vertices, float)
    ends = adjacency[crease]
    length = float(np.linalg.norm(v[ends[:, 0]] - v[ends[:, 1]], axis=1).sum())
    return float(surface.area) / (length * edge)


def smallest_patch(surface: trimesh.Trimesh, angle: float) -> float:
    """Area (mm²) of the smallest patch ``surface`` falls into when cut at its feature lines
    at ``angle`` degrees (the whole area where there is no feature line)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    smooth = surface.face_adjacency[np.degrees(surface.face_adjacency_angles) <= angle]
    n = len(surface.faces)
    graph = sp.coo_matrix((np.ones(len(smooth)), (smooth[:, 0], smooth[:, 1])), shape=(n, n))
    count, patch = connected_components(graph, directed=False)
    return float(np.bincount(patch, surface.area_faces, count).min())


_netgen_always = Before()


def netgen_always() -> AbstractContextManager[None]:
    """Within it, ``plan_mesh`` adds no HXT attempt (``_hxt_first``): every Gmsh mesh has
    Netgen's pass, as before session 40. The benches' "before" (process-wide)."""
    return _netgen_always.taken()


@dataclass(frozen=True)
class MeshPlan:
    """What meshing a surface will do, fixed before it starts: the attempts (in order),
    the expected node count and each attempt's CPU work budget. Everything the result
    depends on besides the surface and the edge: it goes into the cache key. ``skipped``:
    the Gmsh attempts left out, each with the reason."""

    choice: str
    attempts: tuple[MeshAttempt, ...]
    nodes: int
    budgets: tuple[float, ...]
    skipped: tuple[tuple[str, str], ...] = ()

    def key(self) -> list:
        return [self.choice, [[_label(a), round(b, 1)] for a, b in zip(self.attempts, self.budgets, strict=True)]]


def plan_mesh(surface: trimesh.Trimesh, edge: float, attempts=ATTEMPTS, choice: str | None = None) -> MeshPlan:
    """The plan for ``surface`` at ``edge`` mm: ``attempts`` filtered by ``choice``
    (default ``$NAVAPP_MESHER``), without the Gmsh attempts whose failure the surface tells
    in advance (never all of the attempts): feature lines closer than ``FEATURE_SPACING_MIN``
    edges; and, on such a staircase, a larger angle (but the largest) still leaving a patch
    smaller than one mesh triangle (``smallest_patch``). Budgets from the expected node count.

    Where attempts were skipped, the first Gmsh attempt kept is tried first with HXT and no
    Netgen pass (``_hxt_first``): it met the floor on every CT-made liver measured."""
    choice = mesher_choice() if choice is None else choice
    chosen = tuple(a for a in attempts if choice == "auto" or a.method == choice)
    if not chosen:
        raise NavappError(f"mesher {choice!r}: none of the attempts uses it")
    skipped: list[tuple[str, str]] = []
    why_not: dict[MeshAttempt, str] = {}
    for a in chosen:
        if a.method == "gmsh":
            spacing = feature_spacing(surface, a.feature_angle, edge * a.edge_scale)
            if spacing < FEATURE_SPACING_MIN:
                why_not[a] = f"feature lines {spacing:.1f} edges apart"
    if why_not:
        # a staircase: the creases it keeps at larger angles are fragments around patches
        # smaller than one triangle of the mesh, which Gmsh meshes into slivers
        triangle = np.sqrt(3) / 4 * edge ** 2
        # never the last Gmsh angle: a 0.8 × 0.8 × 2 mm CT liver keeps a patch of 0.46 mm² at 90°,
        # yet meshes there above the floor (HXT 5.2°, Netgen's 7.1°), where fTetWild took 179 CPU s
        # for 43,847 nodes (docs/decisions/speed.md, "Issue 49, session 40")
        last = max((a.feature_angle for a in chosen if a.method == "gmsh"), default=None)
        for a in chosen:
            if a.method == "gmsh" and a not in why_not and a.feature_angle != last:
                patch = smallest_patch(surface, a.feature_angle)
                if patch < triangle * a.edge_scale ** 2:
                    why_not[a] = f"a patch of {patch:.2g} mm², under one mesh triangle"
    kept = tuple(a for a in chosen if a not in why_not)
    if kept:
        skipped = [(_label(a), why_not[a]) for a in chosen if a in why_not]
        chosen = _hxt_first(kept) if skipped and not _netgen_always else kept
    nodes = expected_nodes(surface, edge)
    return MeshPlan(choice, chosen, nodes, tuple(work_budget(a, nodes) for a in chosen), tuple(skipped))


def _hxt_first(attempts: tuple[MeshAttempt, ...]) -> tuple[MeshAttempt, ...]:
    """``attempts`` with the first Gmsh attempt run first with HXT and without Netgen's pass
    (``MeshAttempt.volume``), then as it was if that mesh fails the quality floor or Gmsh fails.
    Only on a surface whose plan already skipped attempts (a CT label map's staircase): no
    stored mesh was made on one, and there Netgen's pass was two thirds of the mesher's CPU
    (docs/decisions/speed.md, "Issue 49, session 40")."""
    for i, a in enumerate(attempts):
        if a.method == "gmsh" and a.volume == "delaunay":
            return (*attempts[:i], replace(a, volume="hxt"), *attempts[i:])
    return attempts


def tetrahedralise(surface: trimesh.Trimesh, edge: float = EDGE_MM, seed: int = 0, limit: float | None = None,
                   attempts=ATTEMPTS) -> TetMesh:
    """Tet mesh of the solid bounded by ``surface`` with target edge length ``edge`` mm.

    ``attempts`` are tried in order, each in a child process stopped when it overruns its
    CPU work budget (Gmsh cannot be interrupted from Python and has been seen to hang on
    sharp surfaces): an overrun is a property of the surface, so the next attempt runs. The
    first mesh with no inverted tet and no dihedral angle under ``MIN_DIHEDRAL_DEG`` is
    returned, its nodes (M, 3) mm and tets (E, 4) positively oriented (``mesh_liver`` also
    reports what was tried). ``limit`` (default ``$NAVAPP_MESH_TIMEOUT``, none) is wall
    clock: reaching it raises, it never changes the mesh. Raises ``NavappError`` in one line
    when every attempt failed or the time ran out.
    """
    mesh, _ = _mesh_with_log(surface, edge, seed, limit, attempts)
    return mesh


def _mesh_with_log(surface, edge, seed, limit, attempts, plan: MeshPlan | None = None, on_work=None):
    mesh, log, _ = _mesh_with_report(surface, edge, seed, limit, attempts, plan, on_work)
    return mesh, log


def _mesh_with_report(surface, edge, seed, limit, attempts, plan: MeshPlan | None = None, on_work=None):
    """(mesh, log of the attempts, the mesh's ``quality_report``): the report the floor was
    checked on is the one returned (0.4 CPU s at 26k nodes, once)."""
    if edge <= 0:
        raise NavappError("edge length must be positive")
    if not surface.is_watertight:
        raise NavappError("liver surface is not watertight: cannot mesh its volume")
    plan = plan_mesh(surface, edge, attempts) if plan is None else plan
    limit = time_limit() if limit is None else float(limit)
    deadline = None if limit is None else time.monotonic() + limit
    log: list[dict] = []
    v = np.asarray(surface.vertices, float)
    f = np.asarray(surface.faces, np.int64)
    gmsh_hung = False
    for attempt, budget in zip(plan.attempts, plan.budgets, strict=True):
        if gmsh_hung and attempt.method == "gmsh":
            continue  # a Gmsh hang is a property of the surface, not of the angle
        if on_work is not None:
            on_work(_label(attempt), expected_cpu(attempt, plan.nodes), None)
        t0 = time.perf_counter()
        usage = {"cpu": 0.0}
        try:
            nodes, tets = _run_attempt(v, f, edge * attempt.edge_scale, seed, attempt, budget, deadline, on_work,
                                       usage)
        except _AttemptFailed as exc:
            log.append({"method": _label(attempt), "outcome": str(exc), "cpu_seconds": round(exc.cpu, 1),
                        "seconds": round(time.perf_counter() - t0, 1)})
            gmsh_hung |= exc.over_budget and attempt.method == "gmsh"
            continue
        except _OutOfTime:
            log.append({"method": _label(attempt), "outcome": f"stopped at the {limit:g} s wall-clock limit"})
            raise NavappError(f"meshing did not finish within {limit:g} s of wall clock (tried: "
                              f"{'; '.join(e['method'] + ': ' + e['outcome'] for e in log)}); "
                              "raise or unset NAVAPP_MESH_TIMEOUT") from None
        entry = {"method": _label(attempt), "seconds": round(time.perf_counter() - t0, 1),
                 "cpu_seconds": round(usage["cpu"], 1)}
        mesh = _tidy(nodes, tets)
        mesh, mended = _closed_manifold(mesh)
        if mesh is None:
            log.append({**entry, "outcome": f"boundary not a closed manifold ({mended})"})
            continue
        q = quality_report(mesh)
        entry.update(nodes=q["nodes"], min_dihedral_deg=round(q["min_dihedral_deg"], 2))
        if mended:
            entry["mended"] = mended
        if q["inverted"] or q["tets_below_5deg"] or q["min_dihedral_deg"] < MIN_DIHEDRAL_DEG:
            entry["outcome"] = (f"below the quality floor ({q['inverted']} inverted, {q['tets_below_5deg']} tets "
                                f"under {MIN_DIHEDRAL_DEG:g}°)")
            log.append(entry)
            continue
        entry["outcome"] = "ok"
        log.append(entry)
        return mesh, log, q
    raise NavappError("could not mesh the liver: " + "; ".join(f"{e['method']}: {e['outcome']}" for e in log))


def why(log: list[dict], plan: MeshPlan) -> str:
    """One line: which mesher made the mesh and why that one."""
    ran = log[-1]["method"]
    skipped = ""
    if plan.skipped:
        skipped = "; ".join(f"{label} skipped ({reason})" for label, reason in plan.skipped)
    if plan.choice != "auto":
        return f"{ran}: NAVAPP_MESHER={plan.choice}" + (f"; {skipped}" if skipped else "")
    if len(log) == 1 and not skipped:
        return f"{ran}: first in the chain, meshed above the quality floor"
    return f"{ran}: " + "; ".join([skipped] * bool(skipped) + [f"{e['method']} {e['outcome']}" for e in log[:-1]])


def _label(attempt: MeshAttempt) -> str:
    scale = "" if attempt.edge_scale == 1.0 else f" at {attempt.edge_scale:g} × edge"
    hxt = " HXT" if attempt.volume == "hxt" else ""  # the Delaunay + Netgen attempts keep their labels (cache keys)
    return (f"gmsh {attempt.feature_angle:g}°{hxt}" if attempt.method == "gmsh" else attempt.method) + scale


def _closed_manifold(mesh: TetMesh):
    """(mesh, what was mended) with every pinch of its boundary opened, or (None, why)
    when mending could not make the boundary one closed manifold (``manifold.py``)."""
    defects = boundary_defects(mesh)
    if defects.ok:
        return mesh, ""
    before = float(tet_volumes(mesh.nodes, mesh.tets).sum())
    mended, removed = mend_pinches(mesh)
    left = boundary_defects(mended)
    if not left.ok:
        return None, f"{defects.describe()}; still {left.describe()} after removing {removed} tets"
    lost = 1.0 - float(tet_volumes(mended.nodes, mended.tets).sum()) / before
    return mended, f"{defects.describe()}: opened by removing {removed} tets ({100 * lost:.2g} % of the volume)"


class _AttemptFailed(Exception):
    def __init__(self, message, cpu=0.0, over_budget=False):
        super().__init__(message)
        self.cpu, self.over_budget = cpu, over_budget


class _OutOfTime(Exception):
    """The wall-clock limit passed: an error for the whole run, never a reason to try the next attempt."""


TEMP_PREFIX = "navapp-mesh-"  # a meshing attempt's temporary folder (``mesh_worker.FOLDER_PREFIX``)


def _sweep_stale_folders():
    """Remove ``navapp-mesh-<pid>-*`` folders whose process is gone: a caller killed by
    SIGKILL cannot clean up after itself, and the worker's clean-up process (``mesh_worker``)
    removes its folder unless it was killed too (e.g. the whole process group by SIGKILL)."""

    import psutil

    for folder in Path(tempfile.gettempdir()).glob(f"{TEMP_PREFIX}*-*"):
        pid = folder.name[len(TEMP_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and not psutil.pid_exists(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)


def _cpu_seconds(ps) -> float:
    t = ps.cpu_times()
    return float(t.user + t.system)


def _run_attempt(v, f, edge, seed, attempt: MeshAttempt, budget: float, deadline: float | None = None, on_work=None,
                 usage: dict | None = None):
    """Run one attempt in ``python -m navapp.anatomy.mesh_worker`` (a fresh interpreter:
    forking a process with viser's threads is unsafe, and spawn would re-run the caller's
    script); stop it when it has used ``budget`` CPU seconds (``_AttemptFailed``) or when
    the wall clock passes ``deadline`` (``_OutOfTime``). Returns (nodes, tets); the CPU
    seconds used go to ``usage["cpu"]``."""
    _sweep_stale_folders()
    # the worker's clean-up process waits on this pipe: its write end is this process's alone
    # (not inherited), closed after the folder is removed here, or by the kernel at our death
    watch_r, watch_w = os.pipe() if os.name == "posix" else (None, None)
    try:
        return _attempt_in_folder(v, f, edge, seed, attempt, budget, deadline, on_work, usage, watch_r)
    finally:
        for fd in (watch_r, watch_w):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass


def _attempt_in_folder(v, f, edge, seed, attempt: MeshAttempt, budget: float, deadline: float | None, on_work,
                       usage: dict | None, watch_r: int | None):
    """``_run_attempt`` in its temporary folder; ``watch_r``: the pipe end the worker's
    clean-up process waits on (None where there is none)."""
    import psutil

    with tempfile.TemporaryDirectory(prefix=f"{TEMP_PREFIX}{os.getpid()}-") as tmp:
        src, dst, log = Path(tmp, "in.npz"), Path(tmp, "out.npz"), Path(tmp, "stderr.txt")
        np.savez(src, vertices=v, faces=f, edge=edge, seed=seed, method=attempt.method,
                 feature_angle=attempt.feature_angle, volume=attempt.volume)
        # fTetWild writes a debug file (__tracked_surface.stl) into its working directory:
        # run it in the temporary one, with navapp importable from there
        package_root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ, OMP_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")])))
        command = [sys.executable, "-m", "navapp.anatomy.mesh_worker", str(src), str(dst), str(os.getpid())]
        if watch_r is not None:
            command.append(str(watch_r))
        with log.open("wb") as err:  # a file, not a pipe: a chatty mesher cannot fill it and block
            proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err, env=env, cwd=tmp,
                                    pass_fds=() if watch_r is None else (watch_r,))
        cpu = 0.0
        try:
            ps = psutil.Process(proc.pid)
            while True:
                try:
                    proc.wait(timeout=0.25)
                    break
                except subprocess.TimeoutExpired:
                    pass
                try:
                    cpu = _cpu_seconds(ps)
                except psutil.Error:  # exited between the wait and the reading
                    continue
                if on_work is not None:
                    on_work(None, None, cpu)
                if cpu > budget:
                    raise _AttemptFailed(f"no mesh within its work budget of {budget:.0f} CPU s", cpu, True)
                if deadline is not None and time.monotonic() > deadline:
                    raise _OutOfTime()
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            if usage is not None:
                usage["cpu"] = cpu
        if not dst.exists():
            tail = log.read_text(errors="replace").strip().splitlines()
            raise _AttemptFailed(tail[-1] if tail else f"the mesher exited with status {proc.returncode}", cpu)
        with np.load(dst) as out:
            if "error" in out:
                raise _AttemptFailed(str(out["error"]), cpu)
            return out["nodes"], out["tets"]


def _tidy(nodes, tets) -> TetMesh:
    """Drop orphan nodes, orient every tet positively."""
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    nodes, tets = nodes[used], remap[tets]
    neg = tet_volumes(nodes, tets) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return TetMesh(nodes=np.ascontiguousarray(nodes, float), tets=np.ascontiguousarray(tets))


class _MeshProgress:
    """The meshing bar: the running attempt's CPU seconds against what it is expected to
    take, so its percentage and ETA follow the work done (slower on a busy machine, as
    they should), never the wall clock alone."""

    def __init__(self, desc: str):
        from .. import progress

        self.desc, self.bar, self._progress = desc, None, progress

    def __call__(self, label, expected, cpu):
        if label is not None:  # an attempt starts
            if self.bar is not None:
                self.bar.close()
            self.bar = self._progress.work(f"{self.desc} ({label})", expected)
            return
        if self.bar is not None:
            self.bar.to(min(cpu, 0.99 * self.bar.total))

    def close(self):
        if self.bar is not None:
            self.bar.close()


def mesh_liver(surface: trimesh.Trimesh, edge: float = EDGE_MM, limit: float | None = None,
               plan: MeshPlan | None = None, show: str | None = None) -> tuple[TetMesh, dict]:
    """Mesh and report: returns the mesh and its quality report with ``seconds``,
    ``method`` (the attempt that succeeded), ``mesher`` (the plan and why this method) and
    ``attempts`` (what was tried). ``show``: a progress-bar label."""
    t0 = time.perf_counter()
    plan = plan_mesh(surface, edge) if plan is None else plan
    bar = _MeshProgress(show) if show else None
    try:
        mesh, log, report = _mesh_with_report(surface, edge, 0, limit, plan.attempts, plan, bar)
    finally:
        if bar is not None:
            bar.close()
    report["edge_mm"] = edge
    report["method"] = log[-1]["method"]
    report["mesher"] = {"choice": plan.choice, "expected_nodes": plan.nodes, "why": why(log, plan)}
    report["attempts"] = log
    report["seconds"] = round(time.perf_counter() - t0, 3)
    return mesh, report


@dataclass(frozen=True)
class MeshProvenance:
    """Which mesher made a mesh and why: what a result made on it reports (``result.json``'s
    ``mesher``, ``navapp register --json``), since the mesh is part of the answer. ``cached``:
    the mesh was made by an earlier run with the same key (surface, edge, plan) and loaded."""

    method: str  # the attempt that made the mesh, e.g. "gmsh 40°", "ftetwild at 0.85 × edge"
    why: str  # one line: that method, and why this one (``why``)
    choice: str  # $NAVAPP_MESHER: auto, gmsh or ftetwild
    edge_mm: float
    nodes: int
    cached: bool = False

    @classmethod
    def from_report(cls, report: dict) -> "MeshProvenance":
        """From ``mesh_liver``'s (or the cache's) report."""
        method = str(report.get("method", "unknown"))
        mesher = report.get("mesher") or {}
        return cls(method, str(mesher.get("why", method)), str(mesher.get("choice", "auto")),
                   float(report.get("edge_mm", 0.0)), int(report.get("nodes", 0)), bool(report.get("cached", False)))

    def as_dict(self) -> dict:
        return {"method": self.method, "why": self.why, "choice": self.choice, "edge_mm": self.edge_mm,
                "nodes": self.nodes, "cached": self.cached}


# gmsh 40/60/90° then fTetWild twice, each with pinches mended, checked against the floor,
# each attempt bounded by CPU work (not wall clock)
MESHER_VERSION = "mesh-chain-5"


def cached_tetmesh(surface: trimesh.Trimesh, edge: float = EDGE_MM, cache_root=None) -> tuple[TetMesh, dict]:
    """``mesh_liver`` through the content-addressed cache (key: surface, edge, the mesher
    and its plan). Before meshing, the expected size is checked against the memory budget."""
    from .. import budget, cache

    root = cache.cache_dir() if cache_root is None else cache_root
    plan = plan_mesh(surface, edge)
    key = cache.content_key(MESHER_VERSION, np.asarray(surface.vertices, float), np.asarray(surface.faces),
                            float(edge), plan.key())
    path = root / f"mesh-{key}.npz"
    hit = cache.load(path)
    if hit is not None:
        mesh = TetMesh(hit["nodes"], hit["tets"])
        # the report is stored with the mesh: recomputing it was most of a cached reload
        report = json.loads(str(hit["report"])) if "report" in hit else quality_report(mesh)
        report.update(edge_mm=edge, seconds=0.0, cached=True)
        return mesh, report
    source = surface.metadata.get("file_path")
    try:
        budget.check_mesh(plan.nodes, edge, abs(float(surface.volume)))
        mesh, report = mesh_liver(surface, edge, plan=plan,
                                  show=f"meshing the liver at {edge:g} mm, ~{plan.nodes:,} nodes")
    except NavappError as exc:
        raise NavappError(f"{source}: {exc}" if source else str(exc)) from None
    report["cached"] = False
    cache.save(path, {"nodes": mesh.nodes, "tets": mesh.tets, "report": np.array(json.dumps(report))})
    return mesh, report
