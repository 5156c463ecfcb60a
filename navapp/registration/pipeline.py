"""Register a case folder end to end: mesh → basis → rigid ICP → LIBR → outputs.

Frames: the model lives in the preoperative frame; data arrive in tracker space. Rigid
ICP gives T (model → tracker); LIBR then runs on the data brought into the model frame
by T⁻¹, and every output point is mapped back to tracker space by T.
"""

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from ..anatomy.caseio import Case, write_csv
from ..anatomy.meshing import cached_tetmesh
from ..mechanics.basis import Basis, BasisSettings, load_or_compute_basis
from ..mechanics.interpolation import interpolation_matrix
from .libr import LibrResult, LMOptions, register_libr
from .model import RegistrationModel, build_model, usable_data
from .rigid import TOL_BEFORE_LIBR, RigidResult, rigid_icp
from .rotation import rotation


@dataclass
class Registration:
    model: RegistrationModel
    rigid: RigidResult
    libr: LibrResult | None
    data_model_frame: dict
    seconds: dict = field(default_factory=dict)

    def transform(self, points, beta=None, B=None) -> np.ndarray:
        """Preoperative points (P, 3) → registered positions in tracker space (P, 3).
        ``B``: their interpolation matrix (``interpolation_matrix``), when the caller
        transforms the same points many times (locating them in the mesh dominates)."""
        b = self.libr.beta if (beta is None and self.libr is not None) else beta
        basis = self.model.basis
        points = np.asarray(points, float)
        if b is None:
            return self.rigid.apply(points)
        return self.rigid.apply(deform_points(basis, self.model.centroid, b, points, B))


def deform_points(basis: Basis, centroid, beta, points, B=None) -> np.ndarray:
    """x(β) of eq. 8 for arbitrary preoperative points, displacement interpolated in the mesh."""
    n = basis.Ju.shape[1]
    B = interpolation_matrix(basis.nodes, basis.tets, points) if B is None else B
    u = (basis.Ju @ beta[:n]).reshape(-1, 3)
    R = rotation(beta[n + 3:n + 6])
    return (points - centroid + B @ u) @ R.T + beta[n:n + 3] + centroid


def tre_stats(pred, truth) -> dict:
    d = np.linalg.norm(pred - truth, axis=1)
    return {"mean_mm": float(d.mean()), "sd_mm": float(d.std()), "max_mm": float(d.max()), "n": int(len(d))}


def prepare(case: Case, edge=4.0, k=45, cache_root=None):
    """Mesh, basis and registration model of a case (cached). Returns (model, seconds)."""
    sec = {}
    t = time.perf_counter()
    mesh, _ = cached_tetmesh(case.preop.liver, edge, cache_root)
    sec["mesh"] = time.perf_counter() - t
    t = time.perf_counter()
    basis, _ = load_or_compute_basis(mesh, BasisSettings(k=k), cache_root=cache_root)
    sec["basis"] = time.perf_counter() - t
    t = time.perf_counter()
    model = build_model(basis, case.preop, case.preop.fiducials)
    sec["model"] = time.perf_counter() - t
    return model, sec


def register(model: RegistrationModel, data: dict, deform=True, options: LMOptions | None = None,
             callback=None, cancel=None, beta0=None, rigid: RigidResult | None = None) -> Registration:
    """Rigid initialisation then (unless ``deform`` is False) LIBR.

    Warm start (e.g. after adding an iUS plane): pass the previous ``rigid`` result and
    ``beta0`` = the previous β; ICP is then skipped and LM starts from β0.
    """
    data = usable_data(model, data)
    options = options or LMOptions()
    sec = {}
    t = time.perf_counter()
    if rigid is None:
        rigid = rigid_icp(model, data, options.weights, tol_mm=TOL_BEFORE_LIBR if deform else 1e-4)
    sec["rigid"] = time.perf_counter() - t
    local = {name: rigid.inverse(p) for name, p in data.items()}
    result = None
    if deform:
        t = time.perf_counter()
        result = register_libr(model, local, beta0, options, callback, cancel)
        sec["deformable"] = time.perf_counter() - t
    return Registration(model, rigid, result, local, sec)


def write_outputs(case: Case, reg: Registration, out: Path, extra: dict) -> dict:
    """Registered liver/vessels (PLY), displaced targets (CSV) and result.json."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("liver", "portal", "hepatic"):
        mesh = getattr(case.preop, name)
        if mesh is not None:
            trimesh.Trimesh(reg.transform(mesh.vertices), mesh.faces, process=False).export(out / f"{name}.ply")
    summary = dict(extra)
    if case.targets is not None:
        x0, x1 = case.targets[:, :3], case.targets[:, 3:]
        pred = reg.transform(x0)
        write_csv(out / "targets.csv", np.column_stack([x0, pred]), ("x0", "y0", "z0", "x1", "y1", "z1"))
        summary["tre_rigid"] = tre_stats(reg.rigid.apply(x0), x1)
        if reg.libr is not None:
            summary["tre_deformable"] = tre_stats(pred, x1)
    (out / "result.json").write_text(json.dumps(summary, indent=2))
    return summary
