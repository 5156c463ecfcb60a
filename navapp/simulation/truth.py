"""Force-driven ground-truth deformations, independent of the registration basis.

The truth is solved on its own (finer) tet mesh, driven by loads rather than by the
basis' prescribed control-point displacements, so it is not in the span of the LIBR
basis (no inverse crime).

Loads and supports (mm, Pa): gravity (ρ = 1060 kg/m³) along a direction tilted toward
the released side, optional uniform pressure on the anterior surface (insufflation), and
an optional local tool indentation (``Tool``: a smooth patch pressed in by a prescribed
displacement or by a dead-load pressure). Supports ``"ligaments"``: the posterior bare
area is always held, and so are the left and right triangular ligaments and the
falciform/coronary attachment unless a scene releases them (L, N or R); ``"posterior"``:
every boundary node facing posterior is held (the organ lying on a firm bed);
``"bare_area"``: the bare area alone.
Small deformation: linear elasticity. Large deformation (a scene's ``large = true``):
compressible neo-Hookean hyperelasticity, total Lagrangian, P1 tetrahedra, Newton with
adaptive load stepping and a backtracking line search (``solve_neo_hookean``). The loads
are dead loads (gravity and the anterior pressure act in the reference configuration),
so the problem has a potential energy, which the line search descends.
St-Venant–Kirchhoff was tried first and dropped: it softens in compression and its
Newton failed at the laparoscopic loads (docs/decisions/mechanics.md).
"""

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import scipy.sparse as sp

from ..anatomy.meshing import TetMesh
from ..errors import NavappError
from ..mechanics.fem import Material, shape_gradients, stiffness
from ..mechanics.sparse import Factorisation
from ..mechanics.supports import Supports, outward_normals, supported_nodes  # noqa: F401 (the truth's supports)

RHO = 1060.0  # kg/m³, liver density


class ToolLoad(StrEnum):
    """How a tool indents the surface."""
    DISPLACEMENT = "displacement"  # the patch is moved by the profile (Dirichlet; linear truth only)
    PRESSURE = "pressure"  # a dead-load pressure with the profile, scaled until the truth reaches the depth


@dataclass(frozen=True)
class Tool:
    """A local indentation: a tool tip or retractor pressing on the surface.

    ``centre`` (3,) mm is a boundary point of the undeformed liver, ``direction`` (3,) the
    unit push direction (into the organ); boundary nodes within ``radius_mm`` of the centre
    that face against the push carry the profile w(r) = (1 − (r/R)²)² (a rounded tip, no
    edge at the rim), and the centre moves ``depth_mm`` along ``direction``.
    """
    centre: tuple
    direction: tuple
    radius_mm: float
    depth_mm: float
    load: ToolLoad = ToolLoad.DISPLACEMENT


@dataclass(frozen=True)
class Loading:
    gravity: float = 9.81  # m/s²; 0: no gravity load
    gravity_dir: tuple = (0.0, -1.0, 0.0)  # supine patient: toward posterior
    pressure: float = 0.0  # Pa on the anterior surface (inward)
    release: str = "N"  # which triangular ligament is released: "L", "N" or "R"
    supports: Supports = Supports.LIGAMENTS
    tool: Tool | None = None


def tool_patch(mesh: TetMesh, tool: Tool) -> tuple[np.ndarray, np.ndarray]:
    """The boundary nodes (P,) the tool touches and their profile weights (P,) in (0, 1]."""
    s, n = outward_normals(mesh)
    d = np.asarray(tool.direction, float)
    r = np.linalg.norm(mesh.nodes[s] - np.asarray(tool.centre, float), axis=1)
    on = (r < tool.radius_mm) & (n @ d < -0.2)  # facing the tool: not the far side of a thin lobe
    if not on.any():
        raise NavappError(f"the tool at {np.round(tool.centre, 1).tolist()} touches no boundary node "
                          f"within {tool.radius_mm:g} mm facing it")
    w = (1 - (r[on] / tool.radius_mm) ** 2) ** 2
    return s[on], w


def _body_force(mesh, loading):
    _, vol = shape_gradients(mesh.nodes, mesh.tets)  # mm³
    # ρ g V: kg/m³ · m/s² · mm³ · 1e-9 m³/mm³ = N; K is in Pa·mm, forces in Pa·mm² = 1e-6 N
    w = RHO * loading.gravity * vol * 1e-9 * 1e6  # gravity = 0: no body force
    g = np.asarray(loading.gravity_dir, float)
    g = g / np.linalg.norm(g)
    f = np.zeros((len(mesh.nodes), 3))
    for a in range(4):
        np.add.at(f, mesh.tets[:, a], np.outer(w / 4, g))
    if loading.pressure:
        faces = mesh.boundary_faces()
        tri = mesh.nodes[faces]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) / 2  # area-weighted, mm²
        anterior = nrm[:, 1] / np.linalg.norm(nrm, axis=1) > 0.3
        for a in range(3):
            np.add.at(f, faces[anterior, a], -loading.pressure * nrm[anterior] / 3)
    return f.ravel()


def _dofs(nodes) -> np.ndarray:
    return (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()


def _free_dofs(mesh, loading, extra_fixed=None):
    fixed = np.unique(np.concatenate(list(supported_nodes(mesh, loading.release, loading.supports).values())
                                     + ([] if extra_fixed is None else [extra_fixed])))
    return np.setdiff1d(np.arange(3 * len(mesh.nodes)), _dofs(fixed))


def _tool_pressure(mesh, tool: Tool, nodes, w) -> np.ndarray:
    """Nodal forces (3M,) of a unit-peak pressure with the tool's profile along its push."""
    _, n = outward_normals(mesh)
    areas = np.zeros(len(mesh.nodes))
    faces = mesh.boundary_faces()
    tri = mesh.nodes[faces]
    a = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    np.add.at(areas, faces.ravel(), np.repeat(a / 3, 3))
    f = np.zeros((len(mesh.nodes), 3))
    f[nodes] = np.outer(w * areas[nodes], np.asarray(tool.direction, float))
    return f.ravel()


def _centre_node(mesh, tool: Tool, nodes) -> int:
    return int(nodes[np.argmin(np.linalg.norm(mesh.nodes[nodes] - np.asarray(tool.centre, float), axis=1))])


def tool_force(mesh: TetMesh, loading: Loading, material: Material) -> np.ndarray:
    """The tool's dead-load nodal forces (3M,), Pa·mm²: its profile's pressure scaled so
    that the *linear* solution moves the patch centre ``depth_mm`` along the push (zeros
    without a pressure tool). The large-deformation truth scales it again, until its own
    centre reaches that depth (``solve_neo_hookean``)."""
    tool = loading.tool
    if tool is None or tool.load != ToolLoad.PRESSURE:
        return np.zeros(3 * len(mesh.nodes))
    nodes, w = tool_patch(mesh, tool)
    f = _tool_pressure(mesh, tool, nodes, w)
    K = stiffness(mesh.nodes, mesh.tets, material)
    free = _free_dofs(mesh, loading)
    u = np.zeros(3 * len(mesh.nodes))
    with Factorisation(K[free][:, free]) as F:
        u[free] = F.solve(f[free])
    c = _centre_node(mesh, tool, nodes)
    reach = float(u[_dofs([c])] @ np.asarray(tool.direction, float))
    if reach <= 0:
        raise NavappError("the tool's pressure does not push the surface in (is the patch held by a support?)")
    return f * (tool.depth_mm / reach)


def solve_linear(mesh: TetMesh, loading: Loading, material: Material = Material()) -> np.ndarray:
    """Nodal displacements (M, 3) mm of the loaded, supported liver (linear elasticity)."""
    K = stiffness(mesh.nodes, mesh.tets, material)
    f = _body_force(mesh, loading) + tool_force(mesh, loading, material)
    u = np.zeros(3 * len(mesh.nodes))
    held = None
    if loading.tool is not None and loading.tool.load == ToolLoad.DISPLACEMENT:
        held, w = tool_patch(mesh, loading.tool)
        u[_dofs(held)] = (np.outer(w, np.asarray(loading.tool.direction, float)) * loading.tool.depth_mm).ravel()
    free = _free_dofs(mesh, loading, held)
    with Factorisation(K[free][:, free]) as F:
        u[free] = F.solve(f[free] - K[free] @ u)
    return u.reshape(-1, 3)



class NeoHookean:
    """Compressible neo-Hookean strain energy on a P1 tet mesh, total Lagrangian.

    ψ(F) = μ/2 (I₁ − 3) − μ ln J + λ/2 (ln J)², I₁ = tr FᵀF, J = det F (Pa), with
    λ, μ the Lamé constants of ``material`` (so it is linear elasticity for small strain).
    First Piola–Kirchhoff stress P = μ (F − F⁻ᵀ) + λ ln J F⁻ᵀ; its derivative
    ∂P_iJ/∂F_kL = μ δ_ik δ_JL + (μ − λ ln J) F⁻¹_Jk F⁻¹_Li + λ F⁻¹_Ji F⁻¹_Lk.
    One-point integration is exact for P1 (F constant per tet).

    The shape gradients and the sparsity pattern of the tangent restricted to ``free``
    (DOF indices; all DOFs if None) are computed once, so that each Newton iteration is
    one vectorised evaluation and one ``bincount``.

    Parameters
    ----------
    nodes : (M, 3) mm, reference positions
    tets : (E, 4) node indices
    material : Young's modulus (Pa) and Poisson ratio
    free : (n,) DOF indices (3 node + axis) the tangent is restricted to
    """

    def __init__(self, nodes, tets, material: Material, free=None):
        self.tets = np.asarray(tets)
        self.n_dof = 3 * len(nodes)
        self.lam, self.mu = material.lame()
        self.G, self.vol = shape_gradients(np.asarray(nodes, float), self.tets)  # (E, 4, 3) 1/mm, (E,) mm³
        dof = (3 * self.tets[:, :, None] + np.arange(3)).reshape(len(self.tets), 12)
        self.dof = dof
        self.free = np.arange(self.n_dof) if free is None else np.asarray(free)
        where = np.full(self.n_dof, -1)
        where[self.free] = np.arange(len(self.free))
        fd = where[dof]  # (E, 12): free index of each element DOF, −1 if held
        rows = np.repeat(fd, 12, axis=1).ravel()
        cols = np.tile(fd, (1, 12)).ravel()
        keep = (rows >= 0) & (cols >= 0)
        n = len(self.free)
        key = rows[keep].astype(np.int64) * n + cols[keep]
        uniq, self._slot = np.unique(key, return_inverse=True)
        self._keep = keep
        self._pattern = (uniq // n, uniq % n, n)

    def deformation_gradient(self, u) -> np.ndarray:
        """F = I + Σ_a u_a ⊗ ∇N_a per tet, (E, 3, 3), from nodal displacements u (M, 3) mm."""
        return np.eye(3) + np.einsum("eai,eaj->eij", np.asarray(u).reshape(-1, 3)[self.tets], self.G)

    def energy(self, u) -> float:
        """Strain energy Σ V ψ (Pa·mm³ = 1e-9 J); +inf if any tet is inverted (J ≤ 0)."""
        F = self.deformation_gradient(u)
        J = np.linalg.det(F)
        if not np.all(J > 0):
            return np.inf
        lnJ = np.log(J)
        I1 = np.einsum("eij,eij->e", F, F)
        psi = 0.5 * self.mu * (I1 - 3) - self.mu * lnJ + 0.5 * self.lam * lnJ ** 2
        return float(self.vol @ psi)

    def forces(self, u, tangent=True):
        """Internal nodal forces f_a = V P ∇N_a, (3M,) in Pa·mm², and, if ``tangent``, the
        tangent stiffness ∂f/∂u restricted to ``free`` × ``free`` (CSR, Pa·mm), else None.
        Raises ValueError if a tet is inverted (J ≤ 0): the energy is not defined there."""
        F = self.deformation_gradient(u)
        J = np.linalg.det(F)
        if not np.all(J > 0):
            raise ValueError(f"inverted element (min J = {J.min():.3g})")
        Finv = np.linalg.inv(F)
        FinvT = Finv.transpose(0, 2, 1)
        lnJ = np.log(J)
        P = self.mu * (F - FinvT) + (self.lam * lnJ)[:, None, None] * FinvT
        fe = self.vol[:, None, None] * np.einsum("eij,eaj->eai", P, self.G)  # (E, 4, 3)
        f = np.bincount(self.dof.ravel(), fe.ravel(), minlength=self.n_dof)
        if not tangent:
            return f, None
        # A_iJkL = ∂P_iJ/∂F_kL (class doc); contracted with ∇N_a (J) and ∇N_b (L) per tet.
        # With h_a = F⁻ᵀ ∇N_a (the spatial gradient), the three terms give per (a, b):
        # μ (∇N_a·∇N_b) δ_ik + (μ − λ ln J) h_b,i h_a,k + λ h_a,i h_b,k
        h = np.einsum("eij,eaj->eai", FinvT, self.G)  # (E, 4, 3)
        gg = np.einsum("eaj,ebj->eab", self.G, self.G)
        c1 = (self.mu - self.lam * lnJ) * self.vol
        Ke = c1[:, None, None, None, None] * np.einsum("ebi,eak->eaibk", h, h)
        Ke += (self.lam * self.vol)[:, None, None, None, None] * np.einsum("eai,ebk->eaibk", h, h)
        for i in range(3):
            Ke[:, :, i, :, i] += (self.mu * self.vol)[:, None, None] * gg
        data = np.bincount(self._slot, Ke.reshape(len(self.tets), 144).ravel()[self._keep],
                           minlength=len(self._pattern[0]))
        r, c, n = self._pattern
        return f, sp.csr_matrix((data, (r, c)), shape=(n, n))


def solve_neo_hookean(mesh: TetMesh, loading: Loading, material: Material = Material(), steps=4, tol=1e-8,
                      max_newton=25, min_increment=1.0 / 512, report=None, reached=None) -> np.ndarray:
    """Large-deformation truth: the liver's supports and loads (``Loading``) solved with
    the compressible neo-Hookean model by ``solve_hyperelastic``. Returns (M, 3) mm.

    A pressure tool is applied after the body loads, and only as far as moves the patch
    centre ``depth_mm`` further along the push (within ``DEPTH_TOL``), as the tool alone
    does in the linear truth: a dead load scaled to the linear depth moved a lobe of
    phantom 1 116 mm where the scene declared 45."""
    if loading.tool is not None and loading.tool.load == ToolLoad.DISPLACEMENT:
        raise NavappError("a prescribed tool displacement needs the linear truth: use the pressure tool load")
    f_body = _body_force(mesh, loading)
    f_tool = tool_force(mesh, loading, material)
    free = _free_dofs(mesh, loading)
    tool = loading.tool
    if tool is None or not f_tool.any():
        return solve_hyperelastic(mesh.nodes, mesh.tets, f_body, free, material, steps, tol, max_newton,
                                  min_increment, report, reached)
    c = _dofs([_centre_node(mesh, tool, tool_patch(mesh, tool)[0])])
    push = np.asarray(tool.direction, float)
    u0 = solve_hyperelastic(mesh.nodes, mesh.tets, f_body, free, material, steps, tol, max_newton,
                            min_increment, report).ravel()
    return solve_hyperelastic(mesh.nodes, mesh.tets, f_tool, free, material, steps, tol, max_newton,
                              min_increment, report, reached, base=f_body, start=u0,
                              until=(lambda u: float((u[c] - u0[c]) @ push), tool.depth_mm))


DEPTH_TOL = 0.01  # the truth's tool depth is found to 1 % of the declared one
MAX_LOAD = 8.0  # … within 8 × the load that reaches it in the linear solve


def solve_hyperelastic(nodes, tets, f_ext, free, material: Material = Material(), steps=4, tol=1e-8,
                       max_newton=25, min_increment=1.0 / 512, report=None, reached=None, base=None, start=None,
                       until=None) -> np.ndarray:
    """Static equilibrium f_int(u) = f_ext of the neo-Hookean body, the DOFs not in ``free`` held at 0.

    The load goes from 0 to 1 in increments that start at 1/``steps``. Within an increment,
    Newton with a backtracking line search: a step is halved until the potential energy
    Π(u) = Σ V ψ − f·u decreases (Armijo) or, once energy differences are at round-off,
    the residual norm does; a trial with an inverted tet (J ≤ 0) has Π = ∞. Where the
    tangent is not positive definite (or its step does not descend), a shifted tangent
    K + τ diag|K| gives the step (``_descent_step``). An increment fails if the line search
    finds no decrease or ``max_newton`` iterations do not converge; it is then halved and
    retried from the last converged state, down to ``min_increment``, after which one
    NavappError line says where. After an increment that converged in a few iterations the
    next one doubles (up to 1/``steps``).

    Parameters
    ----------
    nodes : (M, 3) mm; tets : (E, 4)
    f_ext : (3M,) dead-load nodal forces, Pa·mm² (1e-6 N)
    free : (n,) indices of the unconstrained DOFs (3 node + axis)
    tol : converged when the free-DOF residual norm is below ``tol`` × the full load's norm
    report : ``report(load_fraction, iteration, relative_residual)`` sees every Newton iteration
    reached : ``reached(fraction)`` is called after each converged increment (progress: the
        load fraction, or with ``until`` the fraction of its target reached)
    base : (3M,) loads applied in full throughout (already in equilibrium with ``start``)
    start : (3M,) the state the continuation starts from (zeros)
    until : ``(g, target)``: the load is not ramped to 1 but to the fraction λ (up to
        ``MAX_LOAD``) where ``g(u)`` reaches ``target``, found within ``DEPTH_TOL`` × target
        by regula falsi between converged states; a NavappError line where no state does

    Returns
    -------
    (M, 3) nodal displacements, mm
    """
    free = np.asarray(free)
    model = NeoHookean(nodes, tets, material, free)
    base = np.zeros(3 * len(nodes)) if base is None else base
    scale = np.linalg.norm((base + f_ext)[free])
    u = np.zeros(3 * len(nodes)) if start is None else start.copy()
    if not f_ext[free].any():
        return u.reshape(-1, 3)
    end = MAX_LOAD if until else 1.0
    t, dt, first = 0.0, 1.0 / steps, 1.0 / steps
    prev = None  # (load fraction, u) of the previous converged state, for the predictor
    failure = ""

    def solve_at(load, u_from, predictor=None):
        guess = u_from
        if predictor is not None and np.isfinite(model.energy(predictor)):
            guess = predictor
        return _newton(model, f_ext, free, guess, load, scale, tol, max_newton, report, base)

    while t < end - 1e-12:
        dt = min(dt, end - t)
        pred = None if prev is None else u + (u - prev[1]) * dt / (t - prev[0])  # secant along the path
        done, its, failure = solve_at(t + dt, u, pred)
        if done is None:
            dt /= 2
            if dt < min_increment:
                raise NavappError(f"neo-Hookean truth did not converge at load fraction {t:.3f} ({failure}; "
                                  f"increment cut to {dt:.1e})")
            continue
        if until and until[0](done) >= until[1]:
            u = _reach(until, solve_at, (t, u), (t + dt, done), min_increment, reached)
            if reached:
                reached(1.0)
            return u.reshape(-1, 3)
        prev = (t, u)
        u, t = done, t + dt
        if reached:
            reached(min(1.0, until[0](u) / until[1]) if until else t)
        if its <= 6:
            dt = min(2 * dt, first)
    if until:
        raise NavappError(f"the tool's pressure moves the patch centre only {until[0](u):.1f} mm at {end:g} × the "
                          f"load of the linear truth, short of its depth {until[1]:g} mm")
    return u.reshape(-1, 3)


def _reach(until, solve_at, lo, hi, min_increment, reached=None):
    """The converged state between load fractions ``lo`` and ``hi`` (each ``(t, u)``, the
    monitor below and at or above its target) where the monitor is within ``DEPTH_TOL`` of
    the target: regula falsi (Illinois), each trial solved from the state below it.
    ``reached`` sees 1 − (the bracket's smaller miss) / target after every trial: the search
    can take many minutes, and a bar held at the last increment's figure looked stuck."""
    g, target = until
    glo, ghi = g(lo[1]) - target, g(hi[1]) - target
    shown = 1.0 - abs(glo) / target  # what the last increment reported
    # the secant's ends: the one a trial did not replace is halved, every trial (a variant of
    # Illinois that halves more often than it must: a trial or two more on a smooth curve,
    # kept because the six neo-Hookean tool truths of the study were made with it)
    wlo, whi = glo, ghi
    for _ in range(40):
        closer = 1.0 - min(abs(glo), abs(ghi)) / target
        if reached and shown < closer < 1.0:
            reached(closer)
            shown = closer
        if abs(ghi) <= DEPTH_TOL * target:
            return hi[1]
        if abs(glo) <= DEPTH_TOL * target:
            return lo[1]
        width = hi[0] - lo[0]
        if width < min_increment / 64:
            break
        t = lo[0] + width * wlo / (wlo - whi)
        t = min(max(t, lo[0] + 0.05 * width), hi[0] - 0.05 * width)
        done, _, failure = solve_at(t, lo[1], lo[1] + (hi[1] - lo[1]) * (t - lo[0]) / width)
        if done is None:
            raise NavappError(f"neo-Hookean truth did not converge at load fraction {t:.4f} while finding the "
                              f"tool's depth {target:g} mm ({failure})")
        gm = g(done) - target
        if gm < 0:
            lo, glo, wlo = (t, done), gm, gm
            whi /= 2
        else:
            hi, ghi, whi = (t, done), gm, gm
            wlo /= 2
    raise NavappError(f"the tool's pressure snaps the patch centre from {g(lo[1]):.1f} to {g(hi[1]):.1f} mm "
                      f"within a load step of {hi[0] - lo[0]:.1e}: no equilibrium reaches its depth "
                      f"{target:g} mm; declare a shallower depth, or a prescribed displacement with the "
                      f"linear truth (large = false)")


def _descent_step(K, r):
    """The Newton step K⁻¹ r, or, where K is not positive definite (away from a stable
    equilibrium, K is the Hessian of a non-convex energy), the step of K + τ diag|K| with
    the smallest τ in 1e-4 … 1e2 that factorises and descends (Levenberg-style shift).
    Returns (step, r · step, τ) or (None, 0, τ) when no shift works."""
    d = np.abs(K.diagonal())
    tau = 0.0
    while tau <= 1e2:
        A = K if tau == 0 else K + sp.diags(tau * d)
        try:
            with Factorisation(A) as Fz:
                du = Fz.solve(r)
            slope = float(r @ du)  # −dΠ/ds at s = 0: positive for a descent direction
            if np.isfinite(slope) and slope > 0:
                return du, slope, tau
        except Exception:  # noqa: BLE001 - any back end's refusal of a non-SPD matrix means: shift it
            pass
        tau = 1e-4 if tau == 0 else 10 * tau
    return None, 0.0, tau


def _newton(model: NeoHookean, f_ext, free, u, load, scale, tol, max_newton, report, base):
    """Newton with a backtracking line search at load ``base + load · f_ext``, from ``u`` (3M,).
    Returns (u, iterations, "") when converged, or (None, iterations, why) when not."""
    u = u.copy()
    f = base + f_ext * load

    def potential(v):
        e = model.energy(v)
        return e - f @ v if np.isfinite(e) else np.inf

    pi = potential(u)
    if not np.isfinite(pi):
        return None, 0, "inverted element at the start of the increment"
    fint, K = model.forces(u)
    rel = np.inf
    for it in range(1, max_newton + 1):
        r = f[free] - fint[free]
        rel = np.linalg.norm(r) / scale
        if report:
            report(load, it, rel)
        if rel < tol:
            return u, it, ""
        du, slope, _ = _descent_step(K, r)
        if du is None:
            return None, it, "tangent not positive definite even when shifted"
        s = 1.0
        for _ in range(30):
            v = u.copy()
            v[free] += s * du
            pv = potential(v)
            if np.isfinite(pv):
                if pv <= pi - 1e-4 * s * slope:
                    break
                # energy differences at round-off near convergence: accept a residual decrease
                fint_v, _ = model.forces(v, tangent=False)
                if np.linalg.norm(f[free] - fint_v[free]) < (1 - 1e-4 * s) * np.linalg.norm(r):
                    break
            s /= 2
        else:
            return None, it, f"line search found no decrease (residual {rel:.1e})"
        u, pi = v, pv
        fint, K = model.forces(u)
    return None, max_newton, f"{max_newton} Newton iterations (residual {rel:.1e})"
