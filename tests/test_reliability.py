"""navapp under abuse: one run per output folder, outputs that appear whole, settings
checked against their ranges, bounded memory for big inputs, warnings on their own line,
and Dask studies that refuse or honour --scheduler before any work. One test per row of
the issue's table; each was run against the code before its fix and failed there."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import trimesh

from navapp.cli import main
from navapp.errors import InputError, NavappError


def _one_line_error(capsys, code):
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert "\n" not in err and "Traceback" not in err, err
    return err


# ---------------------------------------------------------------- one run per output folder

def _hold_lock(folder):
    """A separate process holding ``folder``'s lock until its stdin closes."""
    code = textwrap.dedent(f"""
        import sys
        from navapp.outputs import folder_lock
        with folder_lock({str(folder)!r}):
            print("held", flush=True)
            sys.stdin.read()
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_register_on_the_same_folder_stops_at_once(tmp_path, capsys):
    """Two `navapp register` on one case at once mixed their outputs; the second now stops
    before reading anything, naming the first."""
    case = tmp_path / "case"
    holder = _hold_lock(case / "registration")
    try:
        err = _one_line_error(capsys, main(["register", str(case)]))
    finally:
        holder.stdin.close()
        holder.wait()
    assert "another navapp run is writing this folder" in err and f"pid {holder.pid}" in err
    # once the first run is gone, the folder is free again (the kernel dropped the lock)
    err = _one_line_error(capsys, main(["register", str(case)]))
    assert "no such case folder" in err


def test_the_lock_is_reentrant_in_one_process(tmp_path):
    from navapp.outputs import folder_lock

    with folder_lock(tmp_path / "out"), folder_lock(tmp_path / "out"):
        pass
    with folder_lock(tmp_path / "out"):  # released: it can be taken again
        pass


def test_a_second_study_appending_to_the_same_results_stops_at_once(tmp_path, capsys):
    """Two `navapp study loads` on one results CSV both skipped the cases already in it and
    wrote the rest twice; the report then averaged the doubled rows without a word. The
    second run now stops before any case is read, naming the first; a study writing another
    file in the same report folder is not held up by it."""
    results = tmp_path / "results"
    holder = _hold_lock(results / "loads.csv")
    try:
        err = _one_line_error(capsys, main(["study", "loads", "--cases", str(tmp_path / "nowhere"),
                                            "--report", str(results)]))
        assert "loads.csv: another navapp run is writing this results file" in err and f"pid {holder.pid}" in err
        # table2 appends to its own CSV in that folder: it goes on (and stops on the missing case)
        err = _one_line_error(capsys, main(["study", "table2", "--cases", str(tmp_path / "nowhere"),
                                            "--results", str(results / "table2.csv"), "--report", str(results)]))
        assert "another navapp run" not in err
    finally:
        holder.stdin.close()
        holder.wait()
    # the lock on the report (released by the refused run) does not linger in this process
    from navapp.outputs import _held

    assert not _held


def test_the_loads_report_folder_is_made_or_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """`study loads --report` to a folder not yet made ran the whole study and then stopped on
    a FileNotFoundError traceback; to a file, the same. Now it is made first, or refused in one
    line before any case is read."""
    from navapp.evaluation import loads

    ran = []
    monkeypatch.setattr(loads, "run_loads", lambda *a: ran.append(a) or 0)
    monkeypatch.setattr(loads, "write_report", lambda results, out: Path(out) / "loads.md")
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    err = _one_line_error(capsys, main(["study", "loads", "--cases", str(tmp_path), "--report", str(a_file)]))
    assert "a-file: --report: not a folder" in err and not ran
    new = tmp_path / "not" / "yet"
    assert main(["--quiet", "study", "loads", "--cases", str(tmp_path), "--report", str(new)]) == 0
    assert new.is_dir() and len(ran) == 1
    # the check is the studies' own, not the loads study's: table2 under a file stops at once too
    err = _one_line_error(capsys, main(["study", "table2", "--cases", str(tmp_path / "nowhere"),
                                        "--report", str(a_file / "sub")]))
    assert "--report:" in err and "is not a folder" in err


def test_a_loads_results_file_with_a_row_written_twice_is_refused(tmp_path):
    """A results file two runs appended to at once (before the lock above) must not be
    averaged as if its repeated rows were more cases."""
    import csv

    from navapp.evaluation.loads import COLUMNS, read_rows

    path = tmp_path / "loads.csv"
    row = dict.fromkeys(COLUMNS, "")
    row.update(case="tool0-a", level="S", method="identity", tre_mean_mm="0.8", tre_max_mm="28.7",
               seconds="0", displacement_mm="0.8", pre_aligned="True", warned="False")
    with path.open("w", newline="") as fh:
        out = csv.DictWriter(fh, COLUMNS)
        out.writeheader()
        out.writerows([row, {**row, "level": "S+all"}])
    assert len(read_rows(path)) == 2
    with path.open("a", newline="") as fh:
        csv.DictWriter(fh, COLUMNS).writerow(row)
    with pytest.raises(InputError, match="tool0-a S identity appears twice"):
        read_rows(path)


def test_outputs_appear_whole_or_not_at_all(tmp_path):
    """A run that fails while writing leaves the previous outputs exactly as they were;
    a run that succeeds replaces them whole (no file of the earlier run left in)."""
    from navapp.outputs import staged

    out = tmp_path / "registration"
    with staged(out) as tmp:
        (tmp / "result.json").write_text("first")
        (tmp / "portal.ply").write_text("first")
    with pytest.raises(RuntimeError), staged(out) as tmp:
        (tmp / "result.json").write_text("second")
        raise RuntimeError("killed while writing")
    assert (out / "result.json").read_text() == "first" and (out / "portal.ply").exists()
    with staged(out) as tmp:
        (tmp / "result.json").write_text("third")
    assert (out / "result.json").read_text() == "third" and not (out / "portal.ply").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["registration"]  # no staging folder left


def test_write_outputs_stages_and_locks(tmp_path, monkeypatch):
    """``write_outputs`` killed half way (here: the second surface fails to export) leaves
    the earlier result in place."""
    from navapp.registration import pipeline

    out = tmp_path / "registration"
    out.mkdir()
    (out / "result.json").write_text('{"run": 1}')
    case = type("C", (), {})()
    case.preop = type("P", (), {"liver": trimesh.creation.box(), "portal": trimesh.creation.box(), "hepatic": None})()
    case.truth = None
    reg = type("R", (), {"quality": None, "transform": staticmethod(lambda x: x)})()
    exports = []

    def export(self, path, *a, **k):
        exports.append(path)
        if len(exports) == 2:
            raise OSError("disk full")
        open(path, "w").write("ply")

    def tumours(folder):  # the command's registered tumours, written before the surfaces
        (folder / "targets").mkdir()
        (folder / "targets" / "tumour1.ply").write_text("run 2")

    monkeypatch.setattr(trimesh.Trimesh, "export", export)
    with pytest.raises(OSError):
        pipeline.write_outputs(case, reg, out, {"run": 2}, tumours)
    assert (out / "result.json").read_text() == '{"run": 1}' and not (out / "liver.ply").exists()
    assert exports[0].parent != out  # written into the staging folder, not into out
    # run 2's tumours were written into out/targets/ in place, beside run 1's result (3-7 mm apart)
    assert not (out / "targets").exists()


# ---------------------------------------------------------------- settings

def _scene(tmp_path, text):
    p = tmp_path / "s.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, message", [
    ("[anatomy]\nphantom = -1\n", "anatomy.phantom = -1 is out of range: must be >= 0"),
    ("[[effects]]\nkind = \"tracking_noise\"\nsd_mm = -5.0\n", "effects[0].sd_mm = -5.0 is out of range: must be >= 0"),
    ("[[effects]]\nkind = \"dropout\"\nfraction = 2.0\n",
     "effects[0].fraction = 2.0 is out of range: must be in [0, 1)"),
    ("[deformation]\ngravity_tilt_deg = 720.0\n", "deformation.gravity_tilt_deg"),
    ("seed = -1\n", "seed = -1 is out of range"),
    ("seed = 4294967296\n", "seed = 4294967296 is out of range: must be in [0, 4.29497e+09]"),  # a traceback after 13 s
    ("[[effects]]\nkind = \"latency\"\nms = nan\n", "effects[0].ms = nan must be a finite number"),
])
def test_scene_values_out_of_range_are_one_line(tmp_path, capsys, text, message):
    """Tracebacks (phantom = -1, sd_mm = -5) or silently accepted (dropout 2.0, tilt 720°)
    before; now one line with the range, exit 2."""
    err = _one_line_error(capsys, main(["simulate", str(_scene(tmp_path, text)), "--out", str(tmp_path / "c")]))
    assert message in err and "s.toml" in err


def test_a_new_effect_key_is_ranged_by_its_name(monkeypatch):
    """An effect parameter added to the table later is checked by the rule of its name."""
    from navapp.simulation import scene

    monkeypatch.setitem(scene.EFFECT_PARAMS, "blur", {"sd_px": float, "angle_deg": float})
    ok = {"effects": [{"kind": "blur", "sd_px": 1.0, "angle_deg": 10.0}]}
    assert scene.parse_scene(ok).effects[0].params == {"sd_px": 1.0, "angle_deg": 10.0}
    with pytest.raises(InputError, match=r"effects\[0\].sd_px = -1.0 is out of range"):
        scene.parse_scene({"effects": [{"kind": "blur", "sd_px": -1.0, "angle_deg": 0.0}]})
    with pytest.raises(InputError, match=r"effects\[0\].angle_deg = 400.0 is out of range: must be in \[-180, 180\]"):
        scene.parse_scene({"effects": [{"kind": "blur", "sd_px": 1.0, "angle_deg": 400.0}]})


def test_every_shipped_scene_is_in_range():
    from navapp.simulation.scene import load_scene, scene_dir

    for path in sorted(scene_dir().glob("*.toml")):
        load_scene(path)


@pytest.mark.parametrize("argv, message", [
    (["register", "CASE", "--k", "100000"], "argument --k: must be at most 1000"),
    (["phantom", "--liver", "-1", "--out", "X"], "argument --liver: must be >= 0"),
    (["mesh", "CASE", "--edge", "nan"], "argument --edge: must be a finite number"),
    (["serve", "--port", "70000"], "argument --port: must be at most 65535"),
    (["study", "table2", "--scheduler", ""], "argument --scheduler: an empty address"),  # was taken as none
])
def test_command_line_values_are_one_line(tmp_path, capsys, argv, message):
    argv = [a.replace("CASE", str(tmp_path)).replace("X", str(tmp_path / "x")) for a in argv]
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = _one_line_error(capsys, e.value.code)
    assert message in err


# ---------------------------------------------------------------- memory

def test_a_big_csv_is_read_in_about_its_own_size(tmp_path):
    """The row-by-row parse kept every row as Python floats: 3.5 GB for 300 MB. Peak
    traced memory is now a small multiple of the array (about 2×: numpy's parse buffer)."""
    import tracemalloc

    from navapp.anatomy.caseio import read_csv

    rows = 200_000
    data = np.random.default_rng(0).normal(size=(rows, 3)) * 50
    path = tmp_path / "anterior.csv"
    np.savetxt(path, data, delimiter=",", fmt="%.6f", header="x,y,z", comments="")
    tracemalloc.start()
    try:
        out = read_csv(path, ("x", "y", "z"), points=True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert out.shape == (rows, 3) and np.allclose(out, data, atol=1e-6)
    assert peak < 4 * out.nbytes, f"peak {peak / 2**20:.0f} MB for a {out.nbytes / 2**20:.0f} MB array"


def test_too_many_points_are_refused_before_parsing(tmp_path, monkeypatch):
    from navapp.anatomy.caseio import read_csv

    monkeypatch.setenv("NAVAPP_MEMORY_MB", "450")  # 50 MB over the base: 3,125 points at 16 KB
    path = tmp_path / "anterior.csv"
    path.write_text("x,y,z\n" + "1,2,3\n" * 6000)
    monkeypatch.setattr(np, "loadtxt", lambda *a, **k: pytest.fail("parsed before the budget check"))
    with pytest.raises(InputError) as err:
        read_csv(path, ("x", "y", "z"), points=True)
    msg = str(err.value)
    assert "\n" not in msg and "6,000 points" in msg and "subsample to at most 3,125 points (e.g. every 2nd row)" in msg


def test_too_many_triangles_are_refused_before_cleanup(tmp_path, monkeypatch):
    from navapp.anatomy import caseio, cleanup

    monkeypatch.setenv("NAVAPP_MEMORY_MB", "445")  # 45 MB over the base: 5,000 triangles
    path = tmp_path / "liver.ply"
    trimesh.creation.icosphere(4, radius=60.0).export(path)  # 5,120 triangles
    monkeypatch.setattr(cleanup, "clean_surface", lambda *a, **k: pytest.fail("cleaned before the budget check"))
    with pytest.raises(InputError, match="5,120 triangles would need .* decimate it to at most 5,000 triangles"):
        caseio.read_surface(path, closed=True)


# ---------------------------------------------------------------- warnings beside bars

def test_a_warning_is_never_glued_to_a_progress_bar(capsys, monkeypatch):
    """A warning raised while a bar is drawn lands on a line of its own on stderr."""
    import warnings

    from navapp import cli, progress

    monkeypatch.setattr(progress, "QUIET", False)

    def command(args):
        with progress.bar(10, "LIBR", "iter") as bar:
            bar.update(3)
            bar.refresh()
            warnings.warn("the data lie on one line", stacklevel=2)
            bar.update(1)

    monkeypatch.setattr(cli, "cmd_mesh", command)
    parser = cli.build_parser
    monkeypatch.setattr(cli, "build_parser", lambda: _with_func(parser(), "mesh", command))
    cli.main(["mesh", "x"])
    lines = capsys.readouterr().err.split("\n")
    hit = [ln for ln in lines if "the data lie on one line" in ln]
    assert hit and hit[0].rsplit("\r", 1)[-1] == "navapp: warning: the data lie on one line", lines


def test_on_a_file_every_warning_has_a_line_of_its_own(capsys, monkeypatch):
    """stderr not a terminal (a log, CI): a bar's states used to stay on one line of ``\r``s,
    and a warning printed after the bar (closed or not) was glued onto that line."""
    import sys

    from navapp import progress

    monkeypatch.setattr(progress, "QUIET", False)
    assert not sys.stderr.isatty()
    with progress.bar(10, "LIBR", "iter") as bar:
        bar.update(3)
        bar.refresh()
        progress.echo("navapp: warning: one while the bar is drawn")
        bar.update(7)
    print("navapp: warning: one after the bar", file=sys.stderr)
    with progress.stage("meshing"):
        pass
    print("navapp: warning: one after a stage", file=sys.stderr)
    with progress.work("meshing (gmsh 40°)", 10.0) as bar:
        bar.to(4.0)
    print("navapp: warning: one after the work bar", file=sys.stderr)
    err = capsys.readouterr().err
    lines = err.split("\n")
    said = [ln for ln in lines if "warning" in ln]
    assert len(said) == 4 and all(ln.startswith("navapp: warning: one ") for ln in said), repr(err)
    assert "\r" not in err and "LIBR" in err, repr(err)


def test_on_a_file_a_bar_with_a_changing_postfix_writes_a_line_per_interval_not_per_update(capsys, monkeypatch):
    """LIBR's bar shows Ω after every iteration; tqdm redraws on a postfix change whatever its
    interval, so a log got a line per iteration (100 lines for one registration)."""
    from navapp import progress

    monkeypatch.setattr(progress, "QUIET", False)
    with progress.bar(100, "LIBR", "iter") as bar:
        for i in range(100):
            bar.update(1)
            bar.set_postfix_str(f"Ω={1.0 / (i + 1):.3e}")
    lines = [ln for ln in capsys.readouterr().err.split("\n") if ln.startswith("LIBR")]
    assert 1 <= len(lines) <= 3, lines


def _with_func(parser, command, fn):
    parser._subparsers._group_actions[0].choices[command].set_defaults(func=fn)
    return parser


# ---------------------------------------------------------------- Dask

@pytest.mark.parametrize("what", ["error-estimate", "next-plane", "hard"])
def test_studies_that_run_locally_refuse_a_scheduler(tmp_path, capsys, what):
    """`--scheduler` was silently ignored (the study ran locally and exited 0)."""
    err = _one_line_error(capsys, main(["study", what, "--scheduler", "tcp://127.0.0.1:1", "--cases",
                                        str(tmp_path), "--report", str(tmp_path / "r")]))
    assert f"study {what} runs on this machine only" in err


@pytest.mark.parametrize("what", ["robustness", "cost", "table2"])
def test_an_unreachable_scheduler_is_found_before_any_work(tmp_path, capsys, monkeypatch, what):
    """robustness and cost ignored --scheduler; table2 found it unreachable only after 42 s
    of local work, leaving an empty CSV. Now: one line before anything runs, no file."""
    pytest.importorskip("distributed", reason="Dask distributed is not installed (pip install -e '.[test]')")
    import socket

    from navapp import cli
    from navapp.evaluation import distribute

    with socket.socket() as s:  # a port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(distribute, "DASK_CONNECT_S", 2)
    monkeypatch.setattr(cli, "_study_cases", lambda args: pytest.fail("work started before the scheduler check"))
    csv = tmp_path / "results.csv"
    err = _one_line_error(capsys, main(["study", what, "--scheduler", f"tcp://127.0.0.1:{port}", "--results",
                                        str(csv), "--report", str(tmp_path / "r")]))
    assert f"--scheduler tcp://127.0.0.1:{port}: no Dask scheduler answers" in err
    assert not csv.exists() and not (tmp_path / "r").exists()


@pytest.mark.parametrize("reply, message", [
    (None, "something accepts connections there but no Dask scheduler answered within 3 s"),
    (b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n", "what answers there is not a Dask scheduler"),
])
def test_a_listener_that_is_not_a_scheduler_is_one_line_in_bounded_time(tmp_path, capsys, monkeypatch, reply,
                                                                         message):
    """A port that accepts and stays silent held table2 for minutes (distributed bounds the TCP
    connect, not the handshake); one that answers HTTP made distributed allocate a length read
    from the reply, reported as "out of memory"."""
    pytest.importorskip("distributed", reason="Dask distributed is not installed (pip install -e '.[test]')")
    import socket
    import threading

    from navapp.evaluation import distribute

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(5)
    held = []

    def serve():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            held.append(conn)
            if reply:
                conn.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()
    monkeypatch.setattr(distribute, "DASK_CONNECT_S", 1)
    monkeypatch.setattr(distribute, "DASK_HANDSHAKE_S", 2)
    try:
        err = _one_line_error(capsys, main(["study", "table2", "--scheduler",
                                            f"tcp://127.0.0.1:{server.getsockname()[1]}",
                                            "--results", str(tmp_path / "r.csv"), "--report",
                                            str(tmp_path / "report")]))  # its own: runs are one per report
    finally:
        server.close()
        for c in held:
            c.close()
    assert message in err and not (tmp_path / "r.csv").exists()


def test_results_csv_is_created_with_its_first_rows(tmp_path):
    from navapp.evaluation.distribute import ResultsCSV

    path = tmp_path / "r.csv"
    with pytest.raises(NavappError), ResultsCSV(path, ("a", "b")) as out:
        out.write([])
        raise NavappError("the run failed before any result")
    assert not path.exists()
    with ResultsCSV(path, ("a", "b")) as out:
        out.write([{"a": 1, "b": 2}])
    with ResultsCSV(path, ("a", "b")) as out:
        out.write([{"a": 3, "b": 4}])
    assert path.read_text().splitlines() == ["a,b", "1,2", "3,4"]


def test_a_basis_too_large_for_memory_is_refused_before_it_is_computed(monkeypatch, tmp_path):
    """The budget sized the mesh at k = 45 only: ``precompute --k 500`` on the demo mesh
    peaked at 4.2 GB against 1.2 GB budgeted, and --k 1000 died in PARDISO with a traceback."""
    from navapp import budget
    from navapp.mechanics import basis as basis_mod

    monkeypatch.setenv("NAVAPP_MEMORY_MB", "3000")
    with pytest.raises(NavappError, match=r"k = 500 on 18,563 mesh nodes would need about 4\.\d GB") as info:
        budget.check_basis(18_563, 500)
    fits = int(str(info.value).split("--k ")[1].split()[0])
    budget.check_basis(18_563, fits)  # the k it names does fit
    with pytest.raises(NavappError):
        budget.check_basis(18_563, fits + 2)
    budget.check_basis(18_563, 45)  # the default on the demo mesh: 1.2 GB
    mesh = type("M", (), {"nodes": np.zeros((18_563, 3)), "tets": np.zeros((1, 4), int)})()
    monkeypatch.setattr(basis_mod, "compute_basis", lambda *a, **k: pytest.fail("computed before the check"))
    with pytest.raises(NavappError, match="k = 500"):
        basis_mod.load_or_compute_basis(mesh, basis_mod.BasisSettings(k=500), cache_root=tmp_path)


def test_pardiso_out_of_memory_is_a_memory_error():
    """PARDISO's "error code -2" (not enough memory) reached the user as a traceback."""
    pypardiso = pytest.importorskip("pypardiso", reason="PARDISO is not available on this platform")
    from navapp.mechanics import sparse

    class Solver:
        def _call_pardiso(self, A, B):
            raise pypardiso.pardiso_wrapper.PyPardisoError(-2)

    with pytest.raises(MemoryError, match="code -2"):
        sparse._pardiso(Solver(), None, None)

    class Other(Solver):
        def _call_pardiso(self, A, B):
            raise pypardiso.pardiso_wrapper.PyPardisoError(-4)

    with pytest.raises(pypardiso.pardiso_wrapper.PyPardisoError):  # other failures stay what they are
        sparse._pardiso(Other(), None, None)


def test_a_scene_that_leaves_no_data_is_one_line(tmp_path, capsys):
    """A dropout fraction of 0.99999 (in range) kept no point: simulate exited 0 with a case
    without intraop data and said nothing."""
    scene = tmp_path / "nodata.toml"
    scene.write_text('[anatomy]\nphantom = 0\n[deformation]\nmesh_edge_mm = 10.0\n[ius]\nplanes = 0\n'
                     '[[effects]]\nkind = "dropout"\nfraction = 0.99999\n')
    err = _one_line_error(capsys, main(["--quiet", "simulate", str(scene), "--out", str(tmp_path / "case")]))
    assert err.startswith(f"navapp: error: {scene}: the scene leaves 0 intraoperative data points after a "
                          "dropout of 0.99999"), err
    assert "lower the dropout fraction" in err and not (tmp_path / "case").exists()


def test_a_scene_with_a_tiny_edge_is_refused_up_front_naming_the_file(tmp_path, capsys, monkeypatch):
    """A scene's deformation.mesh_edge_mm of 0.3 reached the mesher's own check, whose line
    named no file and advised a --edge that simulate does not have."""
    from navapp.simulation import simulate

    monkeypatch.setenv("NAVAPP_MEMORY_MB", "8000")
    monkeypatch.setattr(simulate, "cached_tetmesh", lambda *a, **k: pytest.fail("meshing started"))
    scene = tmp_path / "fine.toml"
    scene.write_text("[anatomy]\nphantom = 0\n[deformation]\nmesh_edge_mm = 0.3\n")
    err = _one_line_error(capsys, main(["--quiet", "simulate", str(scene), "--out", str(tmp_path / "case")]))
    assert err.startswith(f"navapp: error: {scene}: a mesh at 0.3 mm would have about "), err
    assert "set deformation.mesh_edge_mm = " in err and err.endswith(" or coarser"), err


def test_a_viewer_edge_too_fine_is_refused_before_it_starts(phantoms, monkeypatch):
    """``navapp serve --edge 0.3`` simulated the scene first and failed minutes later, at the
    registration mesh; it is now refused before the viewer starts, saying what to use."""
    from navapp.app.core import Core
    from navapp.simulation.scene import demo_scene

    monkeypatch.setenv("NAVAPP_MEMORY_MB", "8000")
    with pytest.raises(InputError, match=r"a mesh at 0.3 mm would .* use --edge [\d.]+ or coarser"):
        Core(demo_scene(), phantoms[0], 0.3, 45)


def test_a_case_simulated_over_another_replaces_it_whole(tmp_path, capsys, cache_root):
    """Simulating a scene without planes over a 16-plane case exited 0 and left the old
    planes' contours, posterior wall, centerlines and images beside the new report, which
    ``navapp register`` then used."""
    from navapp.simulation.scene import parse_scene
    from navapp.simulation.simulate import simulate

    scene = {"name": "over", "anatomy": {"phantom": 0}, "deformation": {"mesh_edge_mm": 10.0},
             "stylus": {"coverage": 0.2}, "ius": {"planes": 2}}
    out = tmp_path / "case"
    simulate(parse_scene(scene), out, cache_root=cache_root)
    assert (out / "intraop" / "us").is_dir() and list((out / "intraop").glob("*_contour.csv"))
    (out / "registration").mkdir()  # an old run's results: about the old case, not this one
    simulate(parse_scene({**scene, "ius": {"planes": 0}}), out, cache_root=cache_root)
    names = sorted(p.name for p in (out / "intraop").iterdir())
    assert not (out / "intraop" / "us").exists() and not (out / "registration").exists(), names
    assert not [n for n in names if "contour" in n or "posterior" in n or "centerline" in n], names
    assert json.loads((out / "truth" / "report.json").read_text())["planes"] == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["case"]  # no staging folder left
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the surgeon's")
    with pytest.raises(InputError, match="holds files and is not a case folder"):
        simulate(parse_scene(scene), mine, cache_root=cache_root)
    assert (mine / "notes.txt").read_text() == "the surgeon's"


def test_a_file_replaced_is_whole_or_as_it_was(tmp_path):
    """``outputs.replaced``, the one way a file is written atomically (the cache's arrays, the
    session's files): complete, it replaces the file by one rename; an error while writing
    leaves the old file and no temporary one behind (the session's files left a ``.tmp`` after
    an error, for the next start to find)."""
    from navapp.cache import load, save
    from navapp.outputs import replaced

    path = tmp_path / "session.json"
    path.write_text("old")
    with replaced(path, "session.json.tmp") as tmp:
        assert tmp == tmp_path / "session.json.tmp"
        tmp.write_text("new")
        assert path.read_text() == "old"  # not before the block ends
    assert path.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["session.json"]
    for name in ("session.json.tmp", None):  # a fixed name, and a fresh unique one
        with pytest.raises(RuntimeError), replaced(path, name) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed while writing")
        assert path.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["session.json"]
    arrays = tmp_path / "entry.npz"
    save(arrays, {"a": np.arange(5.0)})
    assert np.array_equal(load(arrays)["a"], np.arange(5.0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["entry.npz", "session.json"]
