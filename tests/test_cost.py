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
