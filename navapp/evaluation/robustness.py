"""Robustness study: how registration copes with a bad starting pose and with
imprecise salient-feature labels.

Every trial takes one simulated study case at data level S + 3 planes (a seeded random
triple per draw), optionally corrupts the salient labels, then moves all the data by a
rigid offset of a given angle (random axis) and translation (random direction) about the
data centroid. The truth targets are moved by the same offset, so the TRE is measured in
the frame the data now live in; the solver only ever sees the data.

Label noise conditions:
- ``clean``: the data as simulated;
- ``shifted``: each salient feature (falciform, both ridges) slides as a whole 5–10 mm in a
  random direction tangent to the true intraoperative surface, projected back onto it (a
  surgeon who places the ridge a little off);
- ``mislabelled``: 10 % of each salient feature's points become anterior points, and the
  same number of anterior points nearest to that feature take its label.

The true surface is used only to make the corrupted data; it never reaches the solver.
Success: TRE ≤ 1.2 × the same method's zero-offset, clean-label TRE on the same case and
plane triple (so label noise that hurts counts as a failure too).
"""

import csv
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import progress
from ..anatomy.caseio import read_case, read_surface
from ..defaults import EDGE_MM, N_PLANES, K
from ..features import SALIENT
from ..geometry.interpolation import interpolation_matrix
from ..geometry.transforms import apply_rigid, axis_angle
from ..geometry.tre import mean_tre
from ..registration.pipeline import METHODS, prepare, register
from ..simulation.levels import data_level
from .distribute import ResultsCSV, check_scheduler, run_tasks

OFFSETS = ((0.0, 0.0), (5.0, 10.0), (10.0, 20.0), (15.0, 30.0), (20.0, 40.0))  # (degrees, mm)
CONDITIONS = ("clean", "shifted", "mislabelled")
SUCCESS_RATIO = 1.2
BASELINE, DEFAULT = "single-icp", "default"  # what ``navapp study robustness`` and its figure compare
COLUMNS = ("case", "method", "condition", "draw", "angle_deg", "shift_mm", "planes", "tre_mm", "tre_rigid_mm",
           "seconds", "rigid_seconds", "iterations", "stop_reason", "starts", "flagged")


@dataclass(frozen=True)
class Trial:
    """One registration of the design (everything needed to rebuild its data)."""
    case: str
    condition: str
    draw: int
    angle_deg: float
    shift_mm: float

    def key(self, method: str) -> tuple:
        return (self.case, method, self.condition, str(self.draw), f"{self.angle_deg:g}")


def design(case_names, draws=4, offsets=OFFSETS, conditions=CONDITIONS) -> list[Trial]:
    return [Trial(c, cond, d, a, s) for c in case_names for cond in conditions for d in range(draws)
            for a, s in offsets]


def _seed(*parts) -> int:
    """A reproducible seed from strings and numbers (Python's hash() is salted per process)."""
    import zlib

    return zlib.crc32("|".join(map(str, parts)).encode())


def random_rotation(rng, angle_deg) -> np.ndarray:
    """(3, 3) rotation by ``angle_deg`` about a uniformly random axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return axis_angle(axis, np.radians(angle_deg))


def offset_transform(rng, angle_deg, shift_mm, pivot):
    """x ↦ R (x − pivot) + pivot + t with |t| = shift_mm: returns a function of (N, 3) mm."""
    R = random_rotation(rng, angle_deg)
    d = rng.normal(size=3)
    t = shift_mm * d / np.linalg.norm(d)
    return lambda x: apply_rigid(R, pivot, np.asarray(x) - pivot) + t


def shift_labels(data: dict, surface, rng, low_mm=5.0, high_mm=10.0) -> dict:
    """Each salient feature slid as a whole along ``surface`` (trimesh, the true surface)."""
    import trimesh

    out = dict(data)
    for name in SALIENT:
        if name not in data or not len(data[name]):
            continue
        pts = data[name]
        _, _, tri = trimesh.proximity.closest_point(surface, pts.mean(0, keepdims=True))
        n = surface.face_normals[tri[0]]
        d = rng.normal(size=3)
        d -= (d @ n) * n
        d *= rng.uniform(low_mm, high_mm) / np.linalg.norm(d)
        out[name], _, _ = trimesh.proximity.closest_point(surface, pts + d)
    return out


def mislabel(data: dict, rng, fraction=0.1) -> dict:
    """``fraction`` of each salient feature's points swapped with the nearest anterior points."""
    from scipy.spatial import cKDTree

    out = {k: np.array(v) for k, v in data.items()}
    ant = out.get("anterior")
    if ant is None or not len(ant):
        return out
    taken = np.zeros(len(ant), bool)
    moved: list[np.ndarray] = []  # salient points that go to the anterior feature
    for name in SALIENT:
        if name not in out or not len(out[name]):
            continue
        pts = out[name]
        m = max(1, int(round(fraction * len(pts))))
        gone = rng.choice(len(pts), m, replace=False)
        dist, _ = cKDTree(pts).query(ant)
        dist[taken] = np.inf
        come = np.argsort(dist)[:m]
        taken[come] = True
        out[name] = np.vstack([np.delete(pts, gone, axis=0), ant[come]])
        moved.append(pts[gone])
    out["anterior"] = np.vstack([ant[~taken]] + moved)
    return out


def trial_data(case_dir, case, trial: Trial, truth_surface=None, n_planes=N_PLANES):
    """(data, offset function, planes) of a trial: S + 3 planes, label noise, then offset."""

    rng = np.random.default_rng(_seed(trial.case, trial.draw, "planes"))
    planes = tuple(sorted(int(p) for p in rng.choice(n_planes, 3, replace=False)))
    data = data_level(case_dir, "S+planes", planes=planes, case=case)
    noise_rng = np.random.default_rng(_seed(trial.case, trial.draw, trial.condition))
    if trial.condition == "shifted":
        data = shift_labels(data, truth_surface, noise_rng)
    elif trial.condition == "mislabelled":
        data = mislabel(data, noise_rng)
    pivot = np.vstack(list(data.values())).mean(0)
    off_rng = np.random.default_rng(_seed(trial.case, trial.draw, trial.angle_deg, "offset"))
    move = offset_transform(off_rng, trial.angle_deg, trial.shift_mm, pivot)
    return {k: move(v) for k, v in data.items()}, move, planes


@progress.quiet()  # scoped, as table2.run_chunk: a study step must not silence its caller
def run_case(case_dir, trials, methods, edge=EDGE_MM, k=K) -> list[dict]:
    """Every (trial, method) of one case; returns CSV rows."""

    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case, edge, k)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    surface, _ = read_surface(case_dir / "truth" / "liver.ply", closed=False)
    rows = []
    for trial, method in ((t, m) for t in trials for m in methods):
        data, move, planes = trial_data(case_dir, case, trial, surface)
        t0 = time.perf_counter()
        reg = register(model, data, init=METHODS[method]())
        sec = time.perf_counter() - t0
        truth = move(x1)
        assert reg.libr is not None  # every method of the study deforms
        rows.append({
            "case": trial.case, "method": method, "condition": trial.condition, "draw": trial.draw,
            "angle_deg": trial.angle_deg, "shift_mm": trial.shift_mm, "planes": "-".join(map(str, planes)),
            "tre_mm": round(mean_tre(reg.transform(x0, B=B), truth), 4),
            "tre_rigid_mm": round(mean_tre(reg.rigid.apply(x0), truth), 4),
            "seconds": round(sec, 4), "rigid_seconds": round(reg.seconds.get("rigid", 0.0), 4),
            "iterations": reg.libr.iterations, "stop_reason": reg.libr.stop_reason,
            "starts": len(reg.starts) or 1,
            "flagged": " ".join(reg.quality.flagged) if reg.quality is not None else ""})
    return rows


def read_rows(path) -> list[dict]:
    path = Path(path)
    if not path.exists():
        return []
    with path.open() as f:
        return list(csv.DictReader(f))


def run_robustness(case_dirs, results, methods=(BASELINE, DEFAULT), draws=4, workers=1, edge=EDGE_MM, k=K,
                   offsets=OFFSETS, conditions=CONDITIONS, scheduler=None) -> int:
    """Run (or resume) the design; rows are appended to ``results`` (CSV) one case at a time.

    Returns the number of registrations run. One process per case: a case's basis is
    loaded once, and two processes never compute the same cache entry. ``scheduler``: a
    Dask scheduler's address (checked before any work); the cases run on its workers.
    """
    results = Path(results)
    done = {tuple(r[c] for c in ("case", "method", "condition", "draw")) + (f"{float(r['angle_deg']):g}",)
            for r in read_rows(results)}
    work = []
    for d in case_dirs:
        trials = design([Path(d).name], draws, offsets, conditions)
        todo = [t for t in trials if any(t.key(m) not in done for m in methods)]
        if todo:
            work.append((str(d), todo))
    total = sum(len(t) for _, t in work) * len(methods)
    if not total:
        return 0
    if scheduler:
        check_scheduler(scheduler)
    with ResultsCSV(results, COLUMNS) as out, progress.bar(total, "robustness registrations", "reg") as pb:
        tasks = [(d, todo, methods, edge, k) for d, todo in work]
        for rows in run_tasks(run_case, tasks, scheduler, workers or os.cpu_count()):
            rows = [r for r in rows if Trial(r["case"], r["condition"], r["draw"], r["angle_deg"],
                                             r["shift_mm"]).key(r["method"]) not in done]
            out.write(rows)
            pb.update(len(rows))
    return total
