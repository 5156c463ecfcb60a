"""What accuracy costs in time: the settings sweep and its Pareto front."""

import threading

import numpy as np
import pytest

from navapp.evaluation.cost import SWEEP_LEVELS, lm_sweep, pareto_front


def test_pareto_front_against_brute_force():
    rng = np.random.default_rng(0)
    t, e = rng.random(200), rng.random(200)
    front = pareto_front(t, e)
    for i in range(200):
        beaten = any(t[j] <= t[i] and e[j] <= e[i] and (t[j] < t[i] or e[j] < e[i]) for j in range(200))
        assert front[i] == (not beaten)
    # ties are kept, and the fastest and the most accurate points are always on the front
    assert pareto_front([1, 1], [2, 2]).all()
    assert front[np.argmin(t)] and front[np.argmin(e)]


def test_lm_sweep_more_iterations_never_hurt_much(small_model):
    rng = np.random.default_rng(3)
    n = small_model.basis.Ju.shape[1]
    alpha = rng.normal(size=n) * 0.5
    x0 = small_model.basis.nodes
    x1 = x0 + (small_model.basis.Ju @ alpha).reshape(-1, 3)
    feat = small_model.features["liver"]
    X = feat.rest + (feat.BJ.reshape(-1, n) @ alpha).reshape(-1, 3)
    data = {"anterior": X[rng.choice(len(X), 300, replace=False)]}
    seen = []
    rows = lm_sweep(small_model, data, x0, x1, caps=(0, 1, 100), rtols=(1e-1,), on_row=seen.append)
    assert [r.label for r in rows] == ["rigid", "1 it", "100 it", "rtol 0.1"] and seen == rows
    tre = {r.label: r.tre_mean_mm for r in rows}
    assert tre["100 it"] < tre["rigid"] and tre["100 it"] <= tre["1 it"] + 1e-9
    assert rows[1].iterations == 1 and all(r.seconds > 0 for r in rows)
    stop = threading.Event()
    stop.set()
    assert lm_sweep(small_model, data, x0, x1, cancel=stop) == []


def test_cost_study_rows_resume_and_report(tmp_path, cache_root, monkeypatch, capsys):
    import csv as csvmod

    from navapp.evaluation import cost
    from navapp.evaluation.cost import run_cost_study
    from navapp.evaluation.cost_report import write_cost_report
    from navapp.simulation.scene import parse_scene
    from navapp.simulation.simulate import simulate

    case = tmp_path / "c"
    simulate(parse_scene({"name": "c", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
                          "ius": {"planes": 16}}), case, cache_root)
    csv = tmp_path / "cost.csv"
    # TRE at a 12 mm mesh's nodes and two of the three sweep levels (S + all, the longest fit,
    # left out): the same bookkeeping with fewer and shorter registrations and no 4 mm mesh
    small = dict(ks=(8, 12), edges=(14.0, 12.0), caps=(0, 2), rtols=(1e-1,), plane_counts=(0, 2), peers=True,
                 edge0=12.0, k0=12, tre_edge=12.0)
    monkeypatch.setattr(cost, "SWEEP_LEVELS", {lv: SWEEP_LEVELS[lv] for lv in ("S", "S+3")})
    levels = cost.SWEEP_LEVELS
    prepared = []  # (edge, k, whether the cache it built into was empty): precompute is measured cold

    def spy(case_, edge, k, cache_root=None, **kw):
        prepared.append((float(edge), int(k), cache_root is not None and not any(cache_root.iterdir())))
        return real_prepare(case_, edge, k, cache_root=cache_root, **kw)

    real_prepare = cost.prepare
    monkeypatch.setattr(cost, "prepare", spy)
    # the first run is the README's `navapp study cost --cases CASE --results CSV --report DIR`,
    # at the small settings above (its --quick sweep still meshes at 6 and 4 mm)
    import functools
    import json

    from navapp.cli import main

    monkeypatch.setattr(cost, "run_cost_study", functools.partial(run_cost_study, **small))
    assert main(["--quiet", "study", "cost", "--cases", str(case), "--results", str(csv),
                 "--report", str(tmp_path / "rep0")]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    n = printed["rows_added"]
    assert printed["results"] == str(csv) and printed["seconds"] > 0
    assert printed["report"] == str(tmp_path / "rep0" / "cost.md")
    assert "| LIBR |" in (tmp_path / "rep0" / "cost.md").read_text()
    monkeypatch.setattr(cost, "run_cost_study", run_cost_study)
    monkeypatch.setattr(cost, "prepare", real_prepare)

    rows = list(csvmod.DictReader(csv.open()))
    assert n == len(rows) > 0
    sweeps = {r["sweep"] for r in rows}
    assert sweeps == {"k", "edge", "lm", "planes", "peers"}
    assert {r["method"] for r in rows if r["sweep"] == "peers"} == {"rigid ICP", "CPD"}
    assert all(float(r["tre_mean_mm"]) > 0 and float(r["register_s"]) > 0 for r in rows)
    # precompute is measured cold per model: each model built once, into an empty cache
    # (how much longer than a warm load that takes is ``navapp bench precompute``'s to say)
    pre = {(float(r["edge_mm"]), int(r["k"])): float(r["precompute_s"]) for r in rows if r["sweep"] in ("k", "edge")}
    assert set(pre) == {(12.0, 8), (12.0, 12), (14.0, 12)} and all(v > 0 for v in pre.values())
    assert sorted(prepared) == sorted((e, k, True) for e, k in pre), prepared

    # resuming does no work that is done: no precompute, no registration
    calls = {"prepare": 0, "register": 0}

    def counting(name, fn):
        def wrapped(*a, **kw):
            calls[name] += 1
            return fn(*a, **kw)
        return wrapped

    monkeypatch.setattr(cost, "prepare", counting("prepare", cost.prepare))
    monkeypatch.setattr(cost, "register", counting("register", cost.register))
    assert run_cost_study([case], csv, **small) == 0
    assert calls == {"prepare": 0, "register": 0}
    # rows lost from one whole model (edge 14) and one LM setting: exactly that work is redone
    lost = [r for r in rows if r["edge_mm"] == "14.0" or (r["sweep"] == "lm" and r["setting"] == "2 it"
                                                          and r["level"] == "S")]
    assert len(lost) == len(levels) + 1
    with csv.open("w", newline="") as f:
        w = csvmod.DictWriter(f, cost.COST_COLUMNS)
        w.writeheader()
        w.writerows([r for r in rows if r not in lost])
    assert run_cost_study([case], csv, **small) == len(lost)
    assert calls == {"prepare": 2, "register": len(lost)}
    again = list(csvmod.DictReader(csv.open()))
    assert sorted(cost._row_key(r) for r in again) == sorted(cost._row_key(r) for r in rows)

    md = write_cost_report(csv, tmp_path / "rep")
    text = md.read_text()
    assert (tmp_path / "rep" / "cost_tre_vs_time.png").stat().st_size > 0
    assert (tmp_path / "rep" / "cost_tre_vs_k.png").stat().st_size > 0
    assert "| CPD |" in text and "| LIBR |" in text


def test_cost_case_is_quiet_only_while_it_runs(tmp_path, monkeypatch):
    """cost_case hides bars in its own scope and leaves the caller's progress state as it
    was, also when it fails (it used to set progress.QUIET = True for good)."""
    from navapp import progress
    from navapp.evaluation import cost
    from navapp.evaluation.cost import cost_case

    seen = []

    def failing_read(path):
        seen.append(progress.is_quiet())
        raise RuntimeError("stop here")

    monkeypatch.setattr(progress, "QUIET", False)
    monkeypatch.setattr(cost, "read_case", failing_read)
    with pytest.raises(RuntimeError, match="stop here"):
        cost_case(tmp_path / "c", ks=(), edges=(), caps=(0,), rtols=(), plane_counts=(), peers=False)
    assert seen == [True]
    assert progress.QUIET is False and not progress.is_quiet()


def test_the_lm_sweep_keeps_the_fit_s_other_options(monkeypatch):
    """The caps and tolerances vary on the caller's fit (the viewer's robust weights), not on
    a default one."""
    import types

    import navapp.evaluation.cost as cost
    from navapp.registration.libr import LMOptions
    from navapp.registration.objective import robust_weights

    used = []

    def register(model, data, deform=True, options=None):
        used.append(options)
        return types.SimpleNamespace(transform=lambda x, B=None: x, libr=None)

    monkeypatch.setattr(cost, "register", register)
    base = LMOptions(weights=robust_weights(1.0))
    x = np.zeros((3, 3))
    rows = cost.lm_sweep(None, {}, x, x, caps=(0, 100), rtols=(1e-2,), B=object(), base=base)
    assert [r.label for r in rows] == ["rigid", "100 it", "rtol 0.01"]
    assert all(o.weights is base.weights for o in used)
    assert [o.max_iterations for o in used[:2]] == [1, 100] and used[2].rtol == 1e-2
