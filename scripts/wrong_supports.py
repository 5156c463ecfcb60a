"""Declared supports that are wrong (issue 47): the study behind results/wrong_supports.md.

    python scripts/wrong_supports.py run ROWS.jsonl CASE... [--edge MM] [--k K] [--forces]
    python scripts/wrong_supports.py report ROWS.jsonl [--before ROWS.jsonl] [--out MD]

``run``: per local-load case (a scene that held the organ at its supports) and level (S, S+all),
the pose declared as the scene made it (``evaluation.loads.declared_prior``), LIBR on the
free-floating basis (undeclared), on the basis held at the scene's supports (right) and at wrong
ones (ligaments → posterior, posterior → ligaments, bare_area → posterior). One JSON line per
registration, appended to ROWS.jsonl (a case whose six rows are there already is not rerun):
mean TRE over the truth targets and no correction's, answer, warnings, seconds, the answer's
held-out RMS and the held supports' check against the free basis (``Registration.held``).
With ``--forces`` the right and wrong statements are registered with surface forces as the
local-load study's ``libr-forces`` is (``register(surface_forces=True)``, the free-floating model
as the supports' check): each row says so (``forces``), which answer was shown (``answer``: none,
basis or forces) and the choice's held-out figures (``surface_forces``); the undeclared row is the
same registration as without. A rows file holds one kind: the other is refused.

``report``: the table of results/wrong_supports.md from those rows: per supports and level, the
mean TRE, how many answers are more than 0.1 mm worse than the undeclared one with no line
(silently worse) and how many carry a line; with ``--before``, the same rows from the code
before a change beside them. Writes MD (default results/wrong_supports.md), up to the
hand-written "What it shows" that a committed report keeps after it.
"""

import argparse
import json
import sys
import textwrap
import time
import warnings
from collections import defaultdict
from pathlib import Path

WRONG = {"ligaments": "posterior", "posterior": "ligaments", "bare_area": "posterior"}
LEVELS = ("S", "S+all")  # evaluation.loads.LOAD_LEVELS, spelled here so that --help needs no navapp import
HOWS = ("none", "right", "wrong")
WORSE_MM = 0.1  # "silently worse": more than this worse than the undeclared answer, without a line
KEPT = "\n### What it shows"  # where a committed report's own words begin


def fail(message: str):
    sys.exit(f"wrong_supports.py: error: {message}")


def _done(rows_path: Path) -> dict:
    counts: dict = defaultdict(int)
    for row in read_rows(rows_path, missing_ok=True):
        counts[row["case"]] += 1
    return counts


def run(rows_path: Path, cases: list[Path], edge: float | None, k: int | None, forces: bool = False) -> int:
    """Register every case of ``cases`` not yet in ``rows_path`` three ways at both levels (the
    declared statements with surface forces where ``forces``); the number of rows appended."""
    from navapp.anatomy.caseio import read_case
    from navapp.errors import NavappError
    from navapp.evaluation.loads import LOAD_LEVELS, declared_prior
    from navapp.geometry.interpolation import interpolation_matrix
    from navapp.geometry.tre import mean_tre
    from navapp.registration.pipeline import prepare, register
    from navapp.simulation.levels import data_level
    from navapp.simulation.scene import load_scene

    assert LOAD_LEVELS == LEVELS
    for c in cases:  # every folder checked before any work
        if not (c / "preop" / "liver.ply").is_file():
            fail(f"{c}: not a case folder (no preop/liver.ply)")
        if not (c / "truth" / "report.json").is_file():
            fail(f"{c}: not a simulated case (no truth/report.json)")
    kinds = {bool(r.get("forces", False)) for r in read_rows(rows_path, missing_ok=True)}
    if kinds - {forces}:
        fail(f"{rows_path}: its rows are registered {'with' if not forces else 'without'} surface forces; "
             f"{'add' if not forces else 'drop'} --forces or write to another file")
    done = _done(rows_path)
    sizes = {key: v for key, v in (("edge", edge), ("k", k)) if v is not None}
    n = 0
    rows_path.parent.mkdir(parents=True, exist_ok=True)
    with open(rows_path, "a") as fh:
        for c in cases:
            if done[c.name] >= len(LEVELS) * len(HOWS):
                continue
            try:
                case = read_case(c)
                scene = load_scene(case.settings["scene"])
                if scene.supports not in WRONG:
                    fail(f"{c}: its scene holds the organ at {scene.supports!r}, not at one of {', '.join(WRONG)}")
                free, _ = prepare(case, **sizes)
                models = {"none": free, "right": prepare(case, supports=scene.supports, **sizes)[0],
                          "wrong": prepare(case, supports=WRONG[scene.supports], **sizes)[0]}
                x0, x1 = case.need_truth().tre_points(free.basis.nodes)
                B = interpolation_matrix(free.basis.nodes, free.basis.tets, x0)
                prior = declared_prior(c, case)
                for level in LEVELS:
                    data = data_level(c, "S", case=case) if level == "S" else case.intraop
                    for how in HOWS:
                        model = models[how]
                        t = time.perf_counter()
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            with_forces = forces and how != "none"
                            reg = register(model, data, pose_prior=prior, surface_forces=with_forces,
                                           undeclared=free if with_forces else None)
                        row = {"case": c.name, "level": level, "supports": how,
                               "held": model.basis.settings.supports, "scene": scene.supports,
                               "tre": round(mean_tre(reg.transform(x0, B=B), x1), 3),
                               "identity": round(mean_tre(x0, x1), 3), "deformed": reg.deformed,
                               "warnings": [w.text for w in reg.warnings],
                               "seconds": round(time.perf_counter() - t, 2)}
                        if (s := reg.support) is not None:
                            row.update(rigid_heldout=round(s.rigid_mm, 4), deformable_heldout=round(s.deformable_mm, 4),
                                       shown_heldout=round(s.deformable_mm if reg.deformed else s.rigid_mm, 4))
                        if reg.held is not None:
                            row["held_check"] = reg.held.as_dict()
                        if forces:
                            row["forces"] = True
                            row["answer"] = reg.forces.answer.value if reg.forces is not None else \
                                ("basis" if reg.deformed else "none")
                            if reg.forces is not None:
                                row["surface_forces"] = reg.forces.as_dict()
                        fh.write(json.dumps(row) + "\n")
                        fh.flush()
                        n += 1
            except NavappError as exc:
                fail(str(exc))
    return n


def read_rows(path: Path, missing_ok: bool = False) -> list[dict]:
    """The rows of a ``run``'s JSONL; a missing file or a line that is not a row is one line."""
    if not path.is_file():
        if missing_ok and not path.exists():
            return []
        fail(f"{path}: no such rows file")
    rows = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
            row["case"], row["level"], row["supports"], row["tre"], row["warnings"]  # noqa: B018 (the keys used)
        except (ValueError, KeyError, TypeError):
            fail(f"{path}:{i}: not a row of wrong_supports.py run")
        rows.append(row)
    return rows


def tally(rows: list[dict]) -> dict:
    """Per (supports, level): mean TRE, the cases silently worse than the undeclared answer, and
    the number of answers with a line, over the cases with all three rows at that level."""
    by: dict = defaultdict(dict)
    for r in rows:
        by[(r["case"], r["level"])][r["supports"]] = r
    out = {}
    for level in LEVELS:
        keys = sorted(key for key in by if key[1] == level and len(by[key]) == len(HOWS))
        for how in HOWS:
            got = [by[key][how] for key in keys]
            silent = [key[0] for key in keys if how != "none" and not by[key][how]["warnings"]
                      and by[key][how]["tre"] > by[key]["none"]["tre"] + WORSE_MM]
            out[how, level] = {"n": len(keys), "mean": sum(r["tre"] for r in got) / max(len(got), 1),
                               "silent": silent, "warned": sum(1 for r in got if r["warnings"])}
    return out


NAMES = {"none": "undeclared", "right": "right", "wrong": "wrong"}


def report(rows_path: Path, before_path: Path | None, out: Path) -> str:
    """The generated part of results/wrong_supports.md (module doc), written to ``out``."""
    rows = read_rows(rows_path)
    after = tally(rows)
    n = {after["none", level]["n"] for level in LEVELS}
    if not rows or n == {0}:
        fail(f"{rows_path}: no case with all three rows at a level")
    cases = sorted({r["case"] for r in rows})
    with_forces = any(r.get("forces") for r in rows)
    before = tally(read_rows(before_path)) if before_path else None
    made = f"python scripts/wrong_supports.py report {rows_path}" + (f" --before {before_path}" if before_path
                                                                      else "")
    counted = "" if n == {len(cases)} else \
        f"; {' / '.join(str(after['none', level]['n']) for level in LEVELS)} with all three answers at S / S + all"
    plural = "s" if len(cases) > 1 else ""
    head = ["# Declared supports that are wrong (issue 47)", "",
            f"{len(cases)} local-load case{plural} ({cases[0]} … {cases[-1]}{counted}), the pose declared as each "
            "scene made it, registered at S and S + all on the free-floating basis (undeclared), on the basis held "
            "at the scene's own supports (right), and held at wrong ones (posterior for ligaments, ligaments for "
            "posterior, posterior for bare area). Mean TRE over the truth targets, mm; *silently worse*: more than "
            f"{WORSE_MM:g} mm worse than the undeclared answer with no line; *warned*: answers with a line."
            + (" The right and wrong statements are registered with surface forces (the local-load study's "
               "libr-forces: no deformation, the held basis's fit or the forces, whichever predicts held-out "
               "surface data best)." if with_forces else ""), "",
            "    python scripts/wrong_supports.py run ROWS.jsonl CASE…" + (" --forces" if with_forces else ""),
            f"    {made}", ""]
    if before is None:
        head += ["| supports | level | mean TRE | silently worse | warned |", "|---|---|---|---|---|"]
    else:
        old = {(r["case"], r["level"], r["supports"]): r["tre"] for r in read_rows(before_path)}
        moved = [key for r in rows if (key := (r["case"], r["level"], r["supports"])) in old
                 and abs(old[key] - r["tre"]) > 0.0005]
        shared = sum(1 for r in rows if (r["case"], r["level"], r["supports"]) in old)
        head += [f"Before → after: the rows of {before_path} (the code before the change) → {rows_path}; mean TRE "
                 f"changed on {len(moved)} of the {shared} registrations in both"
                 + (f" ({', '.join(' '.join(key) for key in moved[:6])}{' …' if len(moved) > 6 else ''})."
                    if moved else "."), "",
                 "| supports | level | mean TRE | silently worse, before → after | warned, before → after |",
                 "|---|---|---|---|---|"]
    for level in LEVELS:
        for how in HOWS:
            a = after[how, level]
            silent = "—" if how == "none" else str(len(a["silent"]))
            warned = str(a["warned"])
            if before is not None:
                b = before[how, level]
                silent = "—" if how == "none" else f"{len(b['silent'])} → {silent}"
                warned = f"{b['warned']} → {warned}"
            head.append(f"| {NAMES[how]} | {level.replace('+', ' + ')} | {a['mean']:.3f} | {silent} | {warned} |")
    quiet = [f"{name}, {NAMES[how]} at {level.replace('+', ' + ')}: {', '.join(t[how, level]['silent'])}"
             for name, t in (("before", before), ("after", after)) if t is not None
             for level in LEVELS for how in HOWS if t[how, level]["silent"]]
    head += ["", "Silently worse: " + ("; ".join(quiet) if quiet else "none") + "."]
    text = "\n".join(line if line.startswith(("|", "    ")) else textwrap.fill(line, 100, break_on_hyphens=False,
                                                                                   break_long_words=False)
                     for line in head) + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    committed = out.read_text() if out.is_file() else ""
    kept = committed[committed.index(KEPT):] if KEPT in committed else ""
    out.write_text(text + kept)
    return text


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="step", required=True)
    r = sub.add_parser("run", help="register the cases three ways at S and S+all; rows appended to ROWS.jsonl")
    r.add_argument("rows", type=Path, help="JSONL the rows are appended to")
    r.add_argument("cases", type=Path, nargs="+", help="simulated local-load case folders (navapp/scenes/tool*)")
    r.add_argument("--edge", type=float, help="registration mesh element size, mm (default navapp's)")
    r.add_argument("--k", type=int, help="number of control points (default navapp's)")
    r.add_argument("--forces", action="store_true",
                   help="register the declared statements with surface forces (the study's libr-forces)")
    p = sub.add_parser("report", help="the table of results/wrong_supports.md from the rows")
    p.add_argument("rows", type=Path, help="a run's JSONL")
    p.add_argument("--before", type=Path, help="the same run on the code before a change, shown beside it")
    p.add_argument("--out", type=Path, default=Path("results/wrong_supports.md"),
                   help="report written (default results/wrong_supports.md; its \"### What it shows\" is kept)")
    args = ap.parse_args(argv)
    if args.step == "run":
        n = run(args.rows, args.cases, args.edge, args.k, args.forces)
        print(json.dumps({"rows_added": n, "rows": str(args.rows)}))
    else:
        report(args.rows, args.before, args.out)
        print(json.dumps({"report": str(args.out)}))


if __name__ == "__main__":
    main()
