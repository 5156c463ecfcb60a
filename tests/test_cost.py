"""What accuracy costs in time: the settings sweep and its Pareto front."""

import threading

import numpy as np

from navapp.evaluation.cost import lm_sweep, pareto_front


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


def test_cost_study_rows_resume_and_report(tmp_path, cache_root):
    from navapp.evaluation.cost import run_cost_study
    from navapp.evaluation.cost_report import write_cost_report
    from navapp.simulation.scene import parse_scene
    from navapp.simulation.simulate import simulate

    case = tmp_path / "c"
    simulate(parse_scene({"name": "c", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
                          "ius": {"planes": 16}}), case, cache_root, registration_edge=12.0)
    csv = tmp_path / "cost.csv"
    small = dict(ks=(8, 12), edges=(14.0, 12.0), caps=(0, 2), rtols=(1e-1,), plane_counts=(0, 2), peers=True,
                 edge0=12.0, k0=12)
    n = run_cost_study([case], csv, **small)
    import csv as csvmod

    rows = list(csvmod.DictReader(csv.open()))
    assert n == len(rows) > 0
    sweeps = {r["sweep"] for r in rows}
    assert sweeps == {"k", "edge", "lm", "planes", "peers"}
    assert {r["method"] for r in rows if r["sweep"] == "peers"} == {"rigid ICP", "CPD"}
    assert all(float(r["tre_mean_mm"]) > 0 and float(r["register_s"]) > 0 for r in rows)
    # precompute is measured cold per model: the 8-control-point basis is cheaper than 12
    pre = {int(r["k"]): float(r["precompute_s"]) for r in rows if r["sweep"] == "k"}
    assert set(pre) == {8, 12} and all(v > 0 for v in pre.values())
    assert run_cost_study([case], csv, **small) == 0  # resumed: nothing left to do
    md = write_cost_report(csv, tmp_path / "rep")
    text = md.read_text()
    assert (tmp_path / "rep" / "cost_tre_vs_time.png").stat().st_size > 0
    assert (tmp_path / "rep" / "cost_tre_vs_k.png").stat().st_size > 0
    assert "| CPD |" in text and "| LIBR |" in text
