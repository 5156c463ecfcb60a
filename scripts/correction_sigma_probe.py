"""A probe, not a study: would the weighed correction (the mean correction over the mesh
nodes against its own σ, ``support.weigh_correction``, today used only from a kept pose)
tell the deformations that help from those that harm, where the cross-validation cannot?

    python scripts/correction_sigma_probe.py OUT.jsonl LEVEL CASE [CASE ...]

One fresh registration per case at LEVEL (S or S+all) with today's defaults; per case a JSON
line: the TRE of the answer, of the rigid pose, of the deformed fit whatever the answer, of
no correction (pre-aligned cases), the cross-validation's relative gain and z = correction /
σ computed from the fit's own pose. The truth is read only after the fit.
"""
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path


def run(args):
    case_dir, level = args
    from navapp import progress
    progress.QUIET = True
    from navapp.anatomy.caseio import read_case
    from navapp.defaults import EDGE_MM, K
    from navapp.geometry.interpolation import interpolation_matrix
    from navapp.registration import pipeline
    from navapp.registration.pipeline import prepare, register, tre_stats
    from navapp.registration.support import weigh_correction
    from navapp.simulation.levels import study_data
    d = Path(case_dir)
    case = read_case(d)
    model, _ = prepare(case, EDGE_MM, K)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    planes = tuple(range(16)) if level == "S+all" else ()
    data = study_data(d, level, planes, case=case)
    reg = register(model, data)
    rep = json.loads((d / "truth" / "report.json").read_text())
    pre = "tracker_offset" not in rep
    t_ans = tre_stats(reg.transform(x0, B=B), x1)["mean_mm"]
    t_rig = tre_stats(reg.rigid.apply(x0), x1)["mean_mm"]
    t_def = tre_stats(reg.transform(x0, beta=reg.libr.beta, B=B), x1)["mean_mm"]
    t_id = tre_stats(x0, x1)["mean_mm"] if pre else None
    ref = t_id if pre else t_rig
    out = {"case": d.name, "level": level, "pre_aligned": pre, "tre_answer": round(t_ans, 3),
           "tre_rigid": round(t_rig, 3),
           "tre_deformed": round(t_def, 3), "tre_identity": t_id and round(t_id, 3), "reference": round(ref, 3),
           "deformation_helps": t_def < t_rig - 0.1, "warned": bool(reg.warnings)}
    s = reg.support
    if s is not None:
        opts = pipeline._settings(None, None)[0]
        local = {n: reg.rigid.inverse(p) for n, p in data.items()}
        w = weigh_correction(model, local, reg.libr.beta, s, opts)
        out.update(support_rel=round(1 - s.deformable_mm / s.rigid_mm, 3), correction_mm=round(w.correction_mm, 3),
                   sigma_mm=round(w.sigma_mm, 3), z=round(w.correction_mm / w.sigma_mm, 2))
    return out

if __name__ == "__main__":
    outp, level, cases = sys.argv[1], sys.argv[2], sys.argv[3:]
    with ProcessPoolExecutor(2) as pool, open(outp, "a") as f:
        for r in pool.map(run, [(c, level) for c in cases]):
            f.write(json.dumps(r) + "\n")
            f.flush()
            print(json.dumps(r), flush=True)
