"""``navapp register CASE``: the headless registration command."""

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

from .. import progress
from ..argtypes import k_count, positive
from ..defaults import EDGE_MM, LM_MAX_ITERATIONS, K
from ..errors import InputError
from ..fitwarning import FitWarning


def add_register_parser(sub):
    s = sub.add_parser("register", help="register a case folder (rigid ICP + LIBR) and write the results")
    s.add_argument("case", type=Path, help="case folder (docs/design.md §3)")
    s.add_argument("--out", type=Path, help="output folder (default CASE/registration)")
    s.add_argument("--k", type=k_count, default=K, help=f"control points (default {K})")
    s.add_argument("--edge", type=positive(float), default=EDGE_MM, help=f"tet element size, mm (default {EDGE_MM:g})")
    s.add_argument("--no-deform", action="store_true", help="rigid registration only")
    cap = LM_MAX_ITERATIONS
    s.add_argument("--max-iterations", type=positive(int), default=cap, help=f"LM iteration cap (default {cap})")
    s.add_argument("--local-modes", action="store_true",
                   help="add point-load modes under the surface data the first fit leaves off, kept where "
                        "held-out data gain (for local tool loads; off by default, docs/decisions/local-loads.md)")
    s.add_argument("--pose-sd", nargs="+", metavar="MM DEG",
                   help="the data arrive in a frame registered to the preoperative one, to within MM and DEG "
                        "(standard deviations per axis): a pose prior holds what the data cannot determine; "
                        "'none': an unknown frame (the multi-start search). Default: the case's [intraop.pose]")
    s.add_argument("--supports", metavar="HELD",
                   help="where the organ is held (ligaments, posterior, bare_area, or points: the case's "
                        "preop/supports.csv; 'none': free-floating, the paper's basis): every mode of the basis "
                        "vanishes there. Default: the case's [intraop.supports]")
    s.add_argument("--release", metavar="SIDE",
                   help="with --supports ligaments: the ligament released, L, N (none) or R. Default: the case's, "
                        "else N")
    s.add_argument("--support-stiffness", metavar="PA_PER_MM", type=float,
                   help="the supports hold on springs this stiff (Pa per mm of displacement) instead of firmly: "
                        "every mode moves there elastically. Default: the case's [intraop.supports] "
                        "stiffness_pa_per_mm, else held firmly")
    s.add_argument("--surface-forces", action="store_true",
                   help="with declared supports: no deformation, the basis's fit or a force at every surface node, "
                        "whichever predicts held-out surface data best (a local dent; 15-35 s; docs/robustness.md)")
    s.add_argument("--json", action="store_true", help="print a one-line JSON summary on stdout")
    s.set_defaults(func=cmd_register)


def held_supports(args, case):
    """The supports a registration holds its basis at: ``--supports``/``--release``/
    ``--support-stiffness`` where given, else the case's ``[intraop.supports]`` (its points:
    ``preop/supports.csv``); None: free-floating."""
    from ..anatomy.caseio import SUPPORTS_FILE
    from ..mechanics.supports import HeldSupports, case_supports

    points, points_at = case.preop.support_points, Path(args.case) / "preop" / SUPPORTS_FILE
    declared = case_supports(case.settings, Path(args.case) / "case.toml", points)
    held = getattr(args, "supports", None)
    release = getattr(args, "release", None)
    stiffness = getattr(args, "support_stiffness", None)
    if held is None and points is not None and (declared is None or declared.held != "points"):
        # a file the case holds but its declaration does not read would look honoured
        raise InputError("the case has support points but does not declare them: [intraop.supports] held = "
                         "\"points\" in case.toml (or --supports points)", points_at)
    if held is None:
        if declared is None:
            if release is not None:
                raise InputError("--release needs --supports ligaments (or [intraop.supports] in case.toml)")
            if stiffness is not None:
                raise InputError("--support-stiffness needs declared supports (--supports HELD, or "
                                 "[intraop.supports] in case.toml)")
            return None
        if release is None and stiffness is None:
            return declared
        return HeldSupports.parse(declared.held.value, release or declared.release,
                                  "--release" if release is not None else "--support-stiffness",
                                  declared.stiffness if stiffness is None else stiffness, points, points_at)
    if held == "none":
        if release is not None:
            raise InputError("--release with --supports none: a free-floating organ has no ligaments to release")
        if stiffness is not None:
            raise InputError("--support-stiffness with --supports none: a free-floating organ has no supports")
        return None
    if stiffness is None and declared is not None:
        stiffness = declared.stiffness
    return HeldSupports.parse(held, release or (declared.release if declared is not None else "N"), "--supports",
                              stiffness, points, points_at)


def cmd_register(args):
    from ..anatomy.caseio import read_case
    from .libr import LMOptions
    from .local_modes import LocalModeOptions
    from .pipeline import RobustOptions, prepare, register, write_outputs
    from .prior import declared_pose, parse_pose_sd

    t0 = time.perf_counter()
    if getattr(args, "pose_sd", None) is not None:
        try:
            prior = parse_pose_sd(args.pose_sd)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    case = read_case(args.case)
    if getattr(args, "pose_sd", None) is None:
        prior = declared_pose(case.settings)
    if not case.intraop:
        raise InputError("no intraoperative data (intraop/*.csv): nothing to register to", args.case)
    held = held_supports(args, case)
    forces = getattr(args, "surface_forces", False)
    if forces and held is None:
        raise InputError("--surface-forces needs declared supports (--supports HELD, or [intraop.supports] in "
                         "case.toml): a free-floating organ has no unique displacement under a load")
    model, sec = prepare(case, args.edge, args.k, **(held.prepare_args() if held is not None else {}))
    bar = progress.bar(args.max_iterations, "LIBR", "iter")

    def on_iteration(p):
        bar.update(1)
        bar.set_postfix_str(f"Ω={p.omega:.3e}")

    reg = register(model, case.intraop, deform=not args.no_deform,
                   options=LMOptions(max_iterations=args.max_iterations), callback=on_iteration,
                   init=RobustOptions(local_modes=LocalModeOptions() if args.local_modes else None),
                   pose_prior=prior, surface_forces=forces)
    bar.close()
    sec.update(reg.seconds)
    summary: dict = {"case": case.name, "nodes": model.basis.M, "k": model.basis.k,
               "features": {n: len(p) for n, p in reg.data_model_frame.items()},
               "rigid": {"iterations": reg.rigid.iterations, "rms_mm": reg.rigid.rms_mm},
               "supports": None if held is None else held.as_dict()}
    if reg.libr is not None:
        r = reg.libr
        summary.update(iterations=r.iterations, stop_reason=r.stop_reason, omega=r.omega,
                       residuals=r.features, iteration_seconds={k: round(v, 4) for k, v in r.timings.items()})
    sec["total"] = time.perf_counter() - t0
    summary["seconds"] = {k: round(v, 4) for k, v in sec.items()}
    out = args.out or Path(args.case) / "registration"
    write_more = None
    target_lines: list[FitWarning] = []
    if case.preop.targets:
        summary["targets"], write_more, target_lines = _targets(args.case, case, reg, model)
    summary = write_outputs(case, reg, out, summary, write_more, target_lines)
    for line in summary["warnings"]:
        # one line each, on stderr whatever the output format: a wrong answer must not pass silently
        print(f"navapp: warning: {case.name}: {line}", file=sys.stderr)
    if args.json:
        brief: dict = {k: summary[k] for k in ("case", "iterations", "stop_reason", "omega") if k in summary}
        for key in ("tre_rigid", "tre_deformable"):
            if key in summary:
                brief[key] = round(summary[key]["mean_mm"], 3)
        for t in summary.get("targets", []):
            if "tre" in t:
                how = "deformable" if "deformable" in t["tre"] else "rigid"
                brief.setdefault("target_centroid_error_mm", {})[t["name"]] = t["tre"][how]["centroid_mm"]
        brief["seconds"] = summary["seconds"]
        brief["out"] = str(out)
        if "mesher" in summary:
            brief["mesher"] = summary["mesher"]["why"]
        brief["answer"] = summary["answer"]
        brief["ok"] = summary["ok"]
        brief["warning"] = summary["warning"]
        brief["warnings"] = summary["warnings"]
        print(json.dumps(brief))
    else:
        if "mesher" in summary:
            mesher = summary["mesher"]
            print(f"navapp: mesher {mesher['why']}{' (mesh from the cache)' if mesher['cached'] else ''}",
                  file=sys.stderr)
        print(f"registered {case.name}: results in {out}", file=sys.stderr)
        print(json.dumps(summary, indent=2))


def _targets(case_dir, case, reg, model) -> tuple[list[dict], Callable[[Path], None], list[FitWarning]]:
    """Registered targets: per target its centres (preoperative, registered) and, where
    truth is known, errors; the writer of their surfaces (PLY, tracker space) into an
    output folder's ``targets/``, which ``write_outputs`` calls inside its staging folder;
    and the targets' warnings (``support.TargetSupport.warning``), in the targets' order."""
    from ..anatomy.targets import TARGETS_DIR, write_targets
    from ..anatomy.truth import true_targets
    from .support import target_support
    from .targets import registered_targets, target_errors

    targets = case.preop.targets
    moved = registered_targets(reg, targets)
    # the data are in the model frame and the model point is the preoperative centre
    # (deformation is small against the distances that matter here)
    supports = target_support(reg.support, {t.name: t.centre for t in targets}, reg.data_model_frame) \
        if reg.libr is not None else []
    truth, source = true_targets(case_dir, targets, case.truth)
    rigid = registered_targets(reg, targets, rigid=True) if truth is not None else []
    rows, lines = [], []
    for i, (t, m) in enumerate(zip(targets, moved, strict=True)):
        row = {"name": t.name, "kind": "point" if t.surface is None else "surface",
               "diameter_mm": round(t.diameter_mm, 2),
               "centre_preop_mm": [round(float(x), 3) for x in t.centre],
               "centre_registered_mm": [round(float(x), 3) for x in m.centre]}
        if t.surface is not None:
            row["file"] = f"{TARGETS_DIR}/{t.name}.ply"
        if supports:
            row["nearest_data_mm"] = round(supports[i].nearest_data_mm, 1)
            row["determined"] = supports[i].determined
            if (line := supports[i].warning) is not None:
                row["warning"] = line.text
                lines.append(line)
        if truth is not None:
            row["tre"] = {"truth": source, "rigid": target_errors(rigid[i], truth[i])}
            if reg.libr is not None:
                row["tre"]["deformable"] = target_errors(m, truth[i])
        rows.append(row)
    return rows, lambda folder: write_targets(moved, Path(folder) / TARGETS_DIR), lines
