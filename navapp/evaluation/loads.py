"""The local-load study: a tool pressing into a liver held at its supports (``navapp/scenes/tool*``).

Every case is registered at two data levels — the surface data alone (S) and with all its
iUS planes (S+all) — by five methods: no correction (identity), the rigid registration
without and with the rule that keeps a good given pose (``pose.choose_pose``), and LIBR
without the guards (``RobustOptions.unguarded``: the default before local loads were
handled), with them (the default: kept pose, spatial cross-validation against the
rigid answer, ``support``), and with them and local modes (``registration.local_modes``,
not yet the default); then with the pose declared as the scene made it (``rigid-declared``,
``libr-declared``: ``registration.prior``), and with the supports declared as well
(``libr-supported``: the basis held where the scene held the organ, ``mechanics.supports``),
and with a force at every surface node as a third candidate beside no deformation and that
basis's fit (``libr-forces``: ``register(surface_forces=True)``, ``registration.forces``).
One CSV row per registration: mean and max TRE over the truth
targets, the answer given (deformable or rigid), whether a warning was raised and the
first one, and the wall time. ``report`` writes ``loads.md`` and ``loads.png``.

The criterion the study checks: on every case LIBR's mean TRE is at most the identity's
when the data come pre-aligned and at most the rigid answer's otherwise, or a warning
fires; over the set, mean TRE ≤ 0.5 × the identity's.
"""

import csv
import json
import time
import warnings
from pathlib import Path

import numpy as np

from .. import progress
from ..anatomy.caseio import read_case
from ..anatomy.truth import TruthField
from ..errors import InputError
from ..geometry.interpolation import interpolation_matrix
from ..geometry.transforms import apply_inverse
from ..geometry.tre import tre_stats
from ..mechanics.supports import case_supports
from ..registration.forces import Answer
from ..registration.local_modes import LocalModeOptions
from ..registration.pipeline import RobustOptions, prepare, register
from ..registration.pose import POSE_RULE
from ..registration.prior import PosePrior, declared_pose
from ..registration.rotation import rotation_angle
from ..registration.support import SupportOptions
from ..simulation.levels import data_level
from ..simulation.scene import DECLARED_POSE, load_scene
from .distribute import ResultsCSV, run_tasks

LOAD_LEVELS = ("S", "S+all")  # the study's own subset of ``simulation.levels.LEVELS``
METHODS = ("identity", "rigid-unguarded", "rigid", "libr-unguarded", "libr", "libr-local", "rigid-declared",
           "libr-declared", "libr-supported", "libr-forces")
# the pose a pre-aligned case's scene declares when its case.toml says nothing: a fiducial
# registration's few millimetres and degrees (the 1–2 mm / 1–2°)
DECLARED_PRE_ALIGNED = PosePrior(*DECLARED_POSE)


def declared_prior(case_dir: Path, case) -> PosePrior:
    """The pose knowledge of a case as its scene made it: its case.toml's ``[intraop.pose]``;
    else, from the simulator's report, ``DECLARED_PRE_ALIGNED`` for data in the preoperative
    frame and the tracker offset's own size (its translation, mm, and angle, degrees) for an
    offset frame: the surgeon knows how far off the tracker can be, not which way."""
    if (prior := declared_pose(case.settings)) is not None:
        return prior
    rep = json.loads((Path(case_dir) / "truth" / "report.json").read_text())
    if "tracker_offset" not in rep:
        return DECLARED_PRE_ALIGNED
    T = np.array(rep["tracker_offset"], float)
    return PosePrior(max(float(np.linalg.norm(T[:3, 3])), 0.1), max(float(np.degrees(rotation_angle(T[:3, :3]))), 0.1))
def declared_supports(case) -> dict:
    """Where the case says its organ is held (case.toml ``[intraop.supports]``), else where its
    scene held it (its ``supports`` and ``release``: what a surgeon declaring the supports would
    say), as ``prepare``'s keyword arguments."""
    held = case_supports(case.settings, points=case.preop.support_points)
    if held is not None:
        return held.prepare_args()
    scene = load_scene(case.settings["scene"])
    return {"supports": scene.supports, "release": scene.release}


COLUMNS = ("case", "level", "method", "pre_aligned", "covers", "displacement_mm", "tre_mean_mm", "tre_max_mm",
           "answer", "warned", "warning", "seconds", "pose", "turn_deg")


def _case_facts(case_dir: Path, case, nodes: np.ndarray) -> dict:
    """From the simulator's report: pre-aligned or offset, and whether any surface data lie
    on the tool's footprint (within its radius + 10 mm of its centre); the mean true
    displacement (mm) at the registration model's ``nodes`` (M, 3) mm (a case simulated
    before the truth field: its report's, which is at the same nodes)."""
    rep = json.loads((case_dir / "truth" / "report.json").read_text())
    T = np.array(rep.get("tracker_offset", np.eye(4)))
    tool = rep.get("tool")
    covers = None
    if tool is not None:
        pts = np.vstack([p for k, p in case.intraop.items() if k in ("anterior", "posterior", "falciform",
                                                                         "ridge_left", "ridge_right")])
        pre = apply_inverse(T[:3, :3], T[:3, 3], pts)  # back to the preoperative frame
        covers = bool(np.linalg.norm(pre - np.array(tool["centre_mm"]), axis=1).min() < tool["radius_mm"] + 10.0)
    truth = case.need_truth()
    shown = round(float(np.linalg.norm(truth.displacement(nodes), axis=1).mean()), 2) \
        if isinstance(truth, TruthField) else rep["displacement_mm"]["mean"]
    return {"pre_aligned": "tracker_offset" not in rep, "covers": covers, "displacement_mm": shown}


def _init(method: str) -> RobustOptions:
    if method == "libr-local":
        return RobustOptions(local_modes=LocalModeOptions())
    return RobustOptions.unguarded() if method.endswith("unguarded") else RobustOptions()


@progress.quiet()
def run_case(case_dir, methods: tuple[str, ...] = METHODS) -> list[dict]:
    """The rows of one case by ``methods`` (module doc)."""

    case_dir = Path(case_dir)
    case = read_case(case_dir)
    model, _ = prepare(case)
    supported = None  # the basis held at the scene's supports, built when a method asks for it
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    facts = _case_facts(case_dir, case, model.basis.nodes)
    rows = []
    for level in LOAD_LEVELS:
        # S+all is the case's intraop data whole, in the case's order of features: the same arrays
        # as ``study_data``'s S + every plane, but the held-out blocks of the deformation's
        # cross-validation follow the order, and in study_data's two warnings of the quick
        # study changed their figures (the TREs did not)
        data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
        for method in methods:
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # collected from the Registration instead
                pose: str = ""
                turn: str | float = ""
                if method == "identity":
                    pred, answer, lines = x0, "none", []
                else:
                    guarded = not method.endswith("unguarded")
                    declares = method.endswith(("declared", "supported", "forces"))
                    prior = declared_prior(case_dir, case) if declares else None
                    used = model
                    if method in ("libr-supported", "libr-forces"):
                        if supported is None:
                            supported = prepare(case, **declared_supports(case))[0]
                        used = supported
                    reg = register(used, data, deform=method.startswith("libr"), init=_init(method),
                                   pose_prior=prior, surface_forces=method == "libr-forces",
                                   undeclared=model if method == "libr-forces" else None)
                    pred = reg.transform(x0, B=B)
                    answer = "deformable" if reg.deformed else "rigid"
                    if reg.forces is not None and reg.forces.answer is Answer.FORCES:
                        answer = "forces"
                    lines = reg.warnings if guarded else reg.fit_warnings  # unguarded: the fit's own only
                    c = reg.pose_choice
                    if c is not None:  # where the rigid stage's pose came from, and ICP's turn from the given one
                        pose, turn = c.source.value, "" if c.turn_deg is None else round(c.turn_deg, 1)
            sec = time.perf_counter() - t
            st = tre_stats(pred, x1)
            rows.append({"case": case_dir.name, "level": level, "method": method, **facts,
                         "tre_mean_mm": round(st.mean_mm, 3), "tre_max_mm": round(st.max_mm, 2),
                         "answer": answer, "warned": bool(lines), "warning": lines[0].text if lines else "",
                         "seconds": round(sec, 3), "pose": pose, "turn_deg": turn})
    return rows


def run_loads(cases, results: Path, workers: int = 1) -> int:
    """Register every case (``run_case``) and append its rows to ``results`` (CSV); a
    case's methods already in the file are skipped, so an interrupted study resumes and a
    method added later is run alone. Returns rows added."""
    results = Path(results)
    done = set()
    if results.exists():
        with results.open() as fh:
            reader = csv.DictReader(fh)
            if tuple(reader.fieldnames or ()) != COLUMNS:
                raise InputError(f"its columns are not this study's ({', '.join(COLUMNS)}): "
                                 "give a new results file to start again", results)
            done = {(r["case"], r["method"]) for r in reader}
    todo = [(Path(c), methods) for c in cases
            if (methods := tuple(m for m in METHODS if (Path(c).name, m) not in done))]
    for c, _ in todo:  # a bad case stops the study in one line, before any work or progress bar
        read_case(c).need_truth()
    added = 0
    # the file is made with the first case's rows; cases land as they finish (the report sorts them)
    with ResultsCSV(results, COLUMNS) as out, progress.bar(len(todo), "local-load cases", "case") as pb:
        for rows in run_tasks(run_case, todo, workers=workers):
            out.write(rows)
            added += len(rows)
            pb.update(1)
    return added


def read_rows(results: Path) -> list[dict]:
    """The study's rows, typed; a (case, level, method) written twice (two runs appending
    at once, or files joined by hand) is refused: the report would average it twice."""
    with Path(results).open() as fh:
        rows = list(csv.DictReader(fh))
    seen = set()
    for r in rows:
        key = (r["case"], r["level"], r["method"])
        if key in seen:
            raise InputError(f"{' '.join(key)} appears twice (two studies appended to it at once?): "
                             "remove the repeated rows or give a new results file", results)
        seen.add(key)
    for r in rows:
        for k in ("tre_mean_mm", "tre_max_mm", "seconds", "displacement_mm"):
            r[k] = float(r[k])
        for k in ("pre_aligned", "warned"):
            r[k] = r[k] == "True"
        r["covers"] = None if r["covers"] in ("", "None") else r["covers"] == "True"
    return rows


def verdicts(rows: list[dict], method: str = "libr") -> dict:
    """Per (case, level): the method's TRE against the reference it must not exceed
    (identity when pre-aligned, the guarded rigid answer otherwise), and whether it is
    within it, warned, or silently worse."""
    by = {(r["case"], r["level"], r["method"]): r for r in rows}
    out = {}
    for (case, level, m), r in by.items():
        if m != method:
            continue
        ref_method = "identity" if r["pre_aligned"] else "rigid"
        ref = by[(case, level, ref_method)]["tre_mean_mm"]
        ok = r["tre_mean_mm"] <= ref + 1e-9
        out[(case, level)] = {"tre": r["tre_mean_mm"], "reference": ref, "reference_method": ref_method, "ok": ok,
                              "warned": r["warned"], "silent_worse": (not ok) and not r["warned"]}
    return out


def _case_set(cases: list[str]) -> str:
    """Which draw of the local-load scenes the cases are: the study's, on which the guards'
    margins were set, or the held-out one, which no margin saw."""
    if cases and all(c.startswith("tooltest") for c in cases):
        return ("the held-out draw, `python scripts/make_tool_scenes.py --held-out DIR`: other tool and data "
                "sites, other noise; no margin of the guards was set on these")
    draws = {c.split("_")[0] for c in cases}
    if cases and len(draws) == 1 and next(iter(draws)).startswith("tooldraw"):
        k = next(iter(draws))[len("tooldraw"):]
        return (f"held-out draw {k}, `python scripts/make_tool_scenes.py --held-out DIR --draw {k}`: other tool "
                "and data sites, other noise, registered once with the final defaults")
    if cases and all(c.startswith(("tooltest", "tooldraw")) for c in cases):
        return "cases from the held-out draws (`python scripts/make_tool_scenes.py --held-out DIR [--draw K]`)"
    return "`navapp/scenes/tool*.toml`, `scripts/make_tool_scenes.py`"


def _local(row: dict | None) -> str:
    """The per-case table's LIBR-local cell: its TRE, and '!' where it warned."""
    return "—" if row is None else f"{row['tre_mean_mm']:.2f}{' !' if row['warned'] else ''}"


def write_report(results: Path, out_dir: Path) -> Path:
    """``loads.md`` (tables) and ``loads.png`` (TRE per case and method) from the CSV."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_rows(results)
    out_dir = Path(out_dir)
    cases = sorted({r["case"] for r in rows})
    by = {(r["case"], r["level"], r["method"]): r for r in rows}
    lines = ["# Local loads: a tool pressing into a liver held at its supports", "",
             f"{len(cases)} cases ({_case_set(cases)}), registered by "
             "`navapp study loads`. TRE over the truth targets (the nodes of a 4 mm mesh of the preoperative "
             "liver, made when the case was simulated), mm. "
             "*unguarded*: the default before local loads were handled (multi-start ICP, then LIBR); "
             "*guarded*: today's default (a good given pose, or the pose most of the data lie on near it, kept; "
             "the deformation cross-validated against the rigid answer and, from a kept pose, dropped with a "
             "warning where the data do not support it; from ICP's pose it stays, warned unless its correction is "
             f"at least {SupportOptions.z_strong:g} × its own σ; where the answer from ICP's pose is in doubt, "
             "the given pose held when the "
             f"deformable fit there is within {(POSE_RULE.given_ratio - 1) * 100:.0f} % of ICP's, or when ICP's pose "
             f"turns the organ more than {POSE_RULE.tracker_turn_deg:.0f}° from it and leaves most data off the "
             "model); *libr-local*: guarded, with point-load modes under the surface data the first fit leaves "
             f"more than {LocalModeOptions.off_mm:g} mm off, kept where the held-out RMS drops by more than "
             f"{LocalModeOptions.min_gain * 100:.0f} % (the answer's cross-validation from the same folds, each "
             f"with its own sources), and from ICP's pose warned unless the correction is at least "
             f"{SupportOptions.z:g} × its own σ ({SupportOptions.z_strong:g} × where the cross-validation fails; "
             "not the default). "
             "The CSV's `pose` and `turn_deg`: where the rigid stage's pose came from, and ICP's turn.", ""]
    for level in LOAD_LEVELS:
        lv = [r for r in rows if r["level"] == level]
        lines += [f"## {level}", "", "| method | mean TRE | median over cases | max TRE (mean over cases) | "
                  "warning rate | answer deformable | seconds (median) |", "|---|---|---|---|---|---|---|"]
        for m in METHODS:
            mr = [r for r in lv if r["method"] == m]
            if not mr:
                continue
            tre = np.array([r["tre_mean_mm"] for r in mr])
            lines.append(f"| {m} | {tre.mean():.2f} | {np.median(tre):.2f} | "
                         f"{np.mean([r['tre_max_mm'] for r in mr]):.1f} | "
                         f"{np.mean([r['warned'] for r in mr]) * 100:.0f} % | "
                         f"{np.mean([r['answer'] == 'deformable' for r in mr]) * 100:.0f} % | "
                         f"{np.median([r['seconds'] for r in mr]):.2f} |")
        for m in ("libr-unguarded", "libr", "libr-local", "libr-declared", "libr-supported", "libr-forces"):
            v = verdicts(lv, m)
            if not v:
                continue
            mean = np.mean([x["tre"] for x in v.values()])
            # over the method's own cases (a method added later may have run on some of them)
            ident = np.mean([by[(c, level, "identity")]["tre_mean_mm"] for c, _ in v])
            lines += ["", f"**{m}**: within its reference (identity when pre-aligned, rigid otherwise) on "
                      f"{sum(x['ok'] for x in v.values())} of {len(v)} cases; warned on "
                      f"{sum(x['warned'] for x in v.values())}; **silently worse on "
                      f"{sum(x['silent_worse'] for x in v.values())}**; set mean {mean:.2f} mm = "
                      f"{mean / ident:.2f} × identity's {ident:.2f} mm."]
        lines += [""]
    lines += ["## Per case", "", "| case | aligned | data on the dent | mean displacement | level | identity | "
              "rigid (unguarded / guarded) | LIBR unguarded | LIBR guarded | answer | warning | LIBR local | "
              "LIBR, pose declared | LIBR, supports and pose declared | surface forces, supports and pose declared |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        for level in LOAD_LEVELS:
            if (c, level, "libr") not in by:
                continue
            g = by[(c, level, "libr")]
            lines.append(f"| {c} | {'yes' if g['pre_aligned'] else 'offset'} | "
                         f"{'—' if g['covers'] is None else ('yes' if g['covers'] else 'no')} | "
                         f"{g['displacement_mm']:.1f} | {level} | {by[(c, level, 'identity')]['tre_mean_mm']:.2f} | "
                         f"{by[(c, level, 'rigid-unguarded')]['tre_mean_mm']:.2f} / "
                         f"{by[(c, level, 'rigid')]['tre_mean_mm']:.2f} | "
                         f"{by[(c, level, 'libr-unguarded')]['tre_mean_mm']:.2f} | {g['tre_mean_mm']:.2f} | "
                         f"{g['answer']} | {g['warning'][:90]} | {_local(by.get((c, level, 'libr-local')))} | "
                         f"{_local(by.get((c, level, 'libr-declared')))} | "
                         f"{_local(by.get((c, level, 'libr-supported')))} | "
                         f"{_local(by.get((c, level, 'libr-forces')))} |")
    md = out_dir / "loads.md"
    md.write_text("\n".join(lines) + "\n")

    fig, axes = plt.subplots(len(LOAD_LEVELS), 1, figsize=(11, 7), sharex=True)
    x = np.arange(len(cases))
    colours = {"identity": "0.6", "rigid": "#4c72b0", "libr-unguarded": "#dd8452", "libr": "#55a868",
               "libr-local": "#8172b3", "libr-declared": "#c44e52", "libr-supported": "#937860",
               "libr-forces": "#da8bc3"}
    for ax, level in zip(np.atleast_1d(axes), LOAD_LEVELS, strict=True):
        for i, m in enumerate(colours):
            vals = [by[(c, level, m)]["tre_mean_mm"] if (c, level, m) in by else np.nan for c in cases]
            ax.bar(x + (i - (len(colours) - 1) / 2) * 0.11, vals, 0.11, label=m, color=colours[m])
        for j, c in enumerate(cases):
            if (c, level, "libr") in by and by[(c, level, "libr")]["warned"]:
                ax.text(x[j] + 0.16, 0.92, "!", color="crimson", fontsize=9, ha="center",
                        transform=ax.get_xaxis_transform())  # x in data, y in axes units
        ax.set_ylabel(f"{level}: mean TRE (mm)")
        ax.set_yscale("log")
    # above the panels: inside, the legend hid the first cases' warning marks
    axes[0].legend(ncol=5, fontsize=8, loc="lower right", bbox_to_anchor=(1.0, 1.08), frameon=False)
    axes[0].set_title("Local loads: identity, rigid, LIBR unguarded, guarded and with local modes "
                      "('!': guarded LIBR warned)")
    axes[-1].set_xticks(x, cases, rotation=60, fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "loads.png", dpi=120)
    plt.close(fig)
    return md


def study_command(cases, results: Path, report: Path, workers: int = 1) -> None:
    """``navapp study loads``: run (resumably) and report; one JSON line on stdout."""
    t0 = time.perf_counter()
    Path(report).mkdir(parents=True, exist_ok=True)  # checked by the CLI before any study
    n = run_loads(cases, results, workers)
    md = write_report(results, report)
    print(json.dumps({"rows_added": n, "seconds": round(time.perf_counter() - t0, 1), "results": str(results),
                      "report": str(md)}))
