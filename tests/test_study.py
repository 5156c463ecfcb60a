"""The Table II runner: design size, resumability, report."""

import numpy as np
import pytest

from navapp.evaluation.report import markdown
from navapp.evaluation.table2 import read_results, run_table2, scenarios


def test_design_has_the_papers_counts():
    s = scenarios()
    count = {lv: sum(1 for level, _ in s if level == lv) for lv in ("S+1", "S+2", "S+3")}
    assert count == {"S+1": 16, "S+2": 120, "S+3": 560}
    assert len(s) == 1 + 1 + 16 + 120 + 560 + 1 + 1 + 1  # 701 per case, 6,309 for nine
    assert len(set(s)) == len(s)


def test_quick_run_is_resumable_and_reported(tmp_path, cache_root, phantoms):
    from navapp.simulation.scene import parse_scene
    from navapp.simulation.simulate import simulate

    scene = parse_scene({"name": "q", "anatomy": {"phantom": 0},
                         "deformation": {"release": "L", "mesh_edge_mm": 10.0}, "ius": {"planes": 16}})
    case = tmp_path / "q"
    simulate(scene, case, cache_root, registration_edge=12.0)
    csv = tmp_path / "t2.csv"
    n = run_table2([case], csv, workers=1, quick=True, edge=12.0, k=12)
    rows = read_results(csv)
    assert n == len(rows) == 11
    assert all(np.isfinite(float(r["tre_mean_mm"])) for r in rows)
    assert run_table2([case], csv, workers=1, quick=True, edge=12.0, k=12) == 0  # everything done: nothing reruns
    assert len(read_results(csv)) == 11
    md = markdown(rows)
    assert "paper (Table II)" in md and "| q |" in md
    # rows equal registering each scenario on its own (the chunk shares one ICP over the
    # S and S + planes scenarios, which is exact: ICP sees only the stylus features)
    from navapp.anatomy.caseio import read_case
    from navapp.registration.pipeline import prepare, register, tre_stats
    from navapp.simulation.levels import data_level

    c = read_case(case)
    model, _ = prepare(c, 12.0, 12)
    for r in rows:
        if r["level"].startswith("S+"):
            planes = tuple(int(p) for p in r["planes"].split("-"))
            reg = register(model, data_level(case, "S+planes", planes=planes, case=c))
            assert np.isclose(tre_stats(reg.transform(c.targets[:, :3]), c.targets[:, 3:])["mean_mm"],
                              float(r["tre_mean_mm"]), atol=1e-4)


def test_an_unreachable_dask_scheduler_is_one_line(monkeypatch):
    pytest.importorskip("distributed", reason="the study extra (pip install -e '.[study]') is not installed")
    import socket
    import time

    from navapp.errors import NavappError
    from navapp.evaluation import table2

    with socket.socket() as s:  # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(table2, "DASK_CONNECT_S", 2)
    t0 = time.time()
    with pytest.raises(NavappError) as e:
        table2.dask_client(f"tcp://127.0.0.1:{port}")
    assert time.time() - t0 < 30
    msg = str(e.value)
    assert "\n" not in msg and f"127.0.0.1:{port}" in msg and "no Dask scheduler answers" in msg
