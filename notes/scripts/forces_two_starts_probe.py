"""Issue 47, session 42: the forces' fit at the given pose from w = 0 against the same fit
started from the forces fitted with the pose, per λ (and the joint fit itself): Φ, RMS, TRE.

    python notes/scripts/forces_two_starts_probe.py CASE_DIR:LEVEL...

The data in the model frame and the pose term are the ones ``register(surface_forces=True)``
passes to ``choose_deformation`` (captured); LEVEL is S or S+all. Output of the session's run
(before the change, which took the lower Φ of the two starts for the answer):
notes/forces_two_starts_s42.txt."""

import sys
import warnings
from pathlib import Path

from navapp.anatomy.caseio import read_case
from navapp.evaluation.loads import declared_prior, declared_supports
from navapp.geometry.interpolation import interpolation_matrix
from navapp.geometry.tre import mean_tre
from navapp.registration import forces as F
from navapp.registration import pipeline as PL
from navapp.registration.rigid import beta_pose
from navapp.registration.uncertainty import organ_nodes
from navapp.simulation.levels import data_level

CHOOSE = PL.choose_deformation


def probe(case_dir: Path, level: str) -> None:
    case = read_case(case_dir)
    model, _ = PL.prepare(case, **declared_supports(case))
    free, _ = PL.prepare(case)
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)
    B = interpolation_matrix(model.basis.nodes, model.basis.tets, x0)
    data = data_level(case_dir, "S", case=case) if level == "S" else case.intraop
    got = {}

    def spy(forces, model, local, basis_beta, libr_options, *a, **k):
        got.update(local=local, pose=k.get("pose"))
        return CHOOSE(forces, model, local, basis_beta, libr_options, *a, **k)

    PL.choose_deformation = spy
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reg = PL.register(model, data, pose_prior=declared_prior(case_dir, case), surface_forces=True,
                              undeclared=free)
    finally:
        PL.choose_deformation = CHOOSE
    pose = got["pose"]
    sf = F.SurfaceForces(model.basis)
    pf = sf.responses(F.surface_points(got["local"]))

    def tre(wf):
        moved = x0 + B @ sf.field(pf, wf)
        if wf.q is not None:
            moved = beta_pose(wf.q, model.centroid).apply(moved)
        return round(mean_tre(reg.rigid.apply(moved), x1), 3)

    print(case_dir.name, level, "shown", round(mean_tre(reg.transform(x0, B=B), x1), 3), reg.forces.answer,
          reg.forces.energy_weight, flush=True)
    for lam in F.ENERGY_WEIGHTS:
        o = F.ForceOptions(energy_weight=lam)
        joint = sf.fit_weights(pf, lam, None, o, pose)
        ev = F.forces_pose_evidence(sf, pf, joint, pose, organ_nodes(model))
        zero = sf.fit_weights(pf, lam, None, o, pose, held_q=pose.centre)
        warm = sf.fit_weights(pf, lam, None, o, pose, held_q=pose.centre, w0=joint.w)
        print(f"  λ {lam:g} kept_given {ev.kept_given} | joint phi {joint.phi:.3f} rms {joint.rms_mm:.3f} "
              f"TRE {tre(joint)} | held0 phi {zero.phi:.3f} rms {zero.rms_mm:.3f} TRE {tre(zero)} it "
              f"{zero.iterations}/{zero.accepted} | heldwarm phi0 {warm.phi0:.3f} phi {warm.phi:.3f} rms "
              f"{warm.rms_mm:.3f} TRE {tre(warm)}", flush=True)
    sf.close()


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        where, lev = arg.split(":")
        probe(Path(where), lev)
