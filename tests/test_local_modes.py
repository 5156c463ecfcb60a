"""Local modes: the Kelvin point-load modes against the elastic field equations, the energy
matrix extended exactly, and the fold-wise choice on a tool dent the control-point basis
cannot make (navapp's own FE solve of a tool load, data sampled on its surface)."""

import warnings

import numpy as np
import pytest
import trimesh

from navapp.mechanics.fem import Material


def test_kelvin_modes_satisfy_navier_and_grow_toward_the_source():
    """Away from the source the unregularised field satisfies Navier's equation
    μ∇²u + (λ + μ)∇(∇·u) = 0 (central differences of the returned field, not its formula);
    each mode is scaled to its largest displacement, and points along its force."""
    from navapp.mechanics.local_modes import kelvin_modes

    mat = Material(E=3000.0, nu=0.45)
    lam, mu = mat.lame()
    src, x, h = np.zeros(3), np.array([12.0, -7.0, 9.0]), 1e-2
    e = np.eye(3)
    grid = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
    index = {tuple(g): i for i, g in enumerate(grid)}

    def navier(nu):
        """|μ∇²u + (λ + μ)∇(∇·u)| / |μ∇²u| at x, for the field made with Poisson's ratio ``nu``."""
        # one call: the modes are scaled by their largest value over the points given, the same for all
        field = kelvin_modes(x + h * grid, src, nu, eps_mm=0.0, scale_mm=1.0).reshape(-1, 3, 3)

        def u(*steps):  # (3 components, 3 force directions) at x + h Σ steps
            return field[index[tuple(np.sum(steps, axis=0).astype(int))]]

        lap = sum((u(e[a]) + u(-e[a]) - 2 * u(0 * e[a])) / h ** 2 for a in range(3))
        # ∂_a ∂_c u_c by the mixed central difference (the diagonal a = c as a second difference)
        grad_div = np.stack([sum(((u(e[a]) + u(-e[a]) - 2 * u(0 * e[a])) / h ** 2)[c] if a == c else
                                 ((u(e[a], e[c]) - u(e[a], -e[c]) - u(-e[a], e[c]) + u(-e[a], -e[c]))
                                  / (4 * h ** 2))[c] for c in range(3)) for a in range(3)])
        return np.abs(mu * lap + (lam + mu) * grad_div).max() / (mu * np.abs(lap).max())

    assert navier(mat.nu) < 1e-4
    assert navier(0.3) > 1e-2  # the test can fail: a field with another Poisson's ratio is no solution here

    nodes = np.random.default_rng(0).uniform(-40, 40, (400, 3))
    modes = kelvin_modes(nodes, src, mat.nu).reshape(-1, 3, 3)
    assert np.allclose(np.linalg.norm(modes, axis=1).max(0), 5.0)  # MODE_MM each
    near = np.argmin(np.linalg.norm(nodes, axis=1))
    for j in range(3):
        assert np.argmax(np.abs(modes[near, :, j])) == j  # the nearest node moves along the force


def test_appended_modes_extend_the_energy_matrix_exactly(small_basis):
    """``with_modes`` forms only the new rows of eq. 13's matrix; they equal the matrix
    recomputed over every mode, and the old block is untouched."""
    from navapp.mechanics.basis import energy_matrix
    from navapp.mechanics.local_modes import kelvin_modes, with_modes

    b = small_basis
    src = b.nodes[b.surface[0]] * 0.9 + b.nodes.mean(0) * 0.1
    cols = kelvin_modes(b.nodes, src, b.material.nu)
    ext = with_modes(b, cols, [b.surface[0]])
    full = energy_matrix(b.nodes, b.tets, ext.Ju, b.material)
    assert ext.Ju.shape[1] == b.Ju.shape[1] + 3 and ext.k == b.k + 1
    assert np.allclose(ext.energy, full, rtol=1e-9, atol=1e-9 * np.abs(full).max())
    assert np.array_equal(ext.energy[:b.Ju.shape[1], :b.Ju.shape[1]], b.energy)


@pytest.fixture(scope="module")
def tool_dent(small_model, coarse_mesh):
    """A 30 mm tool tip pressed 20 mm into the anterior-most point of phantom 0, held on its
    posterior bed (navapp's FE solve, ``simulation.truth``), and 1.3 points per cm² sampled
    on the deformed surface within 70 mm of the tool, already aligned: (data, nodes (M, 3)
    after the load, interior nodes within 40 mm of the tool, every interior node)."""
    from navapp.simulation.truth import Loading, Supports, Tool, outward_normals, solve_linear

    s, n = outward_normals(coarse_mesh)
    ant = s[n[:, 1] > 0.5]
    c = coarse_mesh.nodes[ant[np.argmax(coarse_mesh.nodes[ant, 1])]]
    tool = Tool(tuple(c), (0.0, -1.0, 0.0), 30.0, 20.0)
    u = solve_linear(coarse_mesh, Loading(gravity=0.0, supports=Supports.POSTERIOR, tool=tool), Material())
    moved = coarse_mesh.nodes + u
    faces = small_model.basis.surface_faces
    surface = trimesh.Trimesh(moved, faces, process=False)
    pts, fi = trimesh.sample.sample_surface_even(surface, 6000, seed=1)
    rest = trimesh.Trimesh(coarse_mesh.nodes, faces, process=False).triangles_center[fi]
    keep = (np.linalg.norm(rest - c, axis=1) < 70.0) & (surface.face_normals[fi][:, 1] > 0.0)
    inner = np.setdiff1d(np.arange(len(coarse_mesh.nodes)), s)
    near = inner[np.linalg.norm(coarse_mesh.nodes[inner] - c, axis=1) < 40.0]
    return {"anterior": pts[keep]}, moved, near, inner


def test_a_tool_dent_the_basis_cannot_make_is_fitted_with_local_modes(small_model, tool_dent):
    """The control-point basis leaves the dent's data 1.8 mm RMS off and bends the organ to
    share the misfit out: its fit moves the interior farther from the truth than no
    correction. Local modes under the points it leaves off are kept by the held-out blocks,
    fit the data to under half the residual, and bring the interior under the dent to less
    than half its displacement. The answer shown is never worse than no correction."""
    from navapp.registration.local_modes import LocalModeOptions
    from navapp.registration.pipeline import RobustOptions, register

    data, moved, near, inner = tool_dent
    rest = small_model.basis.nodes
    ident = {k: np.linalg.norm(moved[i] - rest[i], axis=1).mean() for k, i in (("near", near), ("all", inner))}

    def fitted(reg, idx):  # the deformable fit, whether or not it is the answer shown
        return np.linalg.norm(reg.transform(rest[idx], beta=reg.libr.beta) - moved[idx], axis=1).mean()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = register(small_model, data)
        local = register(small_model, data, init=RobustOptions(local_modes=LocalModeOptions()))
    assert ident["near"] > 5.0 and base.local_modes is None
    assert base.libr.features["anterior"]["rms_mm"] > 1.5
    assert fitted(base, inner) > ident["all"] and fitted(base, near) > 0.5 * ident["near"]

    lm = local.local_modes
    assert lm.adopted and len(lm.nodes) >= 1 and lm.heldout_extended_mm < 0.95 * lm.heldout_base_mm
    assert local.model.basis.Ju.shape[1] == small_model.basis.Ju.shape[1] + 3 * len(lm.nodes)
    assert local.libr.features["anterior"]["rms_mm"] < 0.5 * base.libr.features["anterior"]["rms_mm"]
    assert fitted(local, near) < 0.5 * ident["near"] and fitted(local, inner) < ident["all"]
    shown = np.linalg.norm(local.transform(rest[inner]) - moved[inner], axis=1).mean()
    assert shown <= ident["all"] + 1e-9
    assert local.seconds["local_modes"] > 0 and "local_modes" not in base.seconds
    # the answer's cross-validation is the folds' own (each with its own sources), not one in
    # which the sources placed from all the data saw the held-out block
    assert local.support.deformable_mm == lm.heldout_extended_mm
    assert base.support.deformable_mm == pytest.approx(lm.heldout_base_mm, abs=1e-12)


def test_a_deformation_the_basis_makes_gets_no_local_modes(small_model):
    """Data moved by the basis' own modes: the first fit leaves too few points off to place a
    source; with noise on them, the held-out blocks gain nothing from the modes placed. The
    answer is today's, bit for bit, either way."""
    from navapp.registration.local_modes import LocalModeOptions
    from navapp.registration.pipeline import RobustOptions, register

    rest = small_model.features["liver"].rest
    front = rest[:, 1] > np.percentile(rest[:, 1], 40)
    alpha = np.zeros(small_model.basis.Ju.shape[1])
    alpha[::7] = 1.5
    moved = rest[front] + (small_model.features["liver"].B @ (small_model.basis.Ju @ alpha).reshape(-1, 3))[front]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = register(small_model, {"anterior": moved})
        local = register(small_model, {"anterior": moved}, init=RobustOptions(local_modes=LocalModeOptions()))
    assert local.local_modes is not None and not local.local_modes.adopted
    assert local.model is small_model
    assert local.local_modes.nodes == []  # the fit leaves too few points off to place a source
    probe = small_model.basis.nodes
    assert np.array_equal(local.transform(probe), base.transform(probe))

    # with 3 mm of noise many points stay off: sources are placed, and the folds refuse them
    # (noise is not a dent); their cross-validation of today's basis is the default's own
    noisy = moved + np.random.default_rng(2).normal(0.0, 3.0, moved.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = register(small_model, {"anterior": noisy})
        local = register(small_model, {"anterior": noisy}, init=RobustOptions(local_modes=LocalModeOptions()))
    assert local.local_modes.nodes and not local.local_modes.adopted and local.model is small_model
    for a, b in ((local.support, base.support), *zip(local.support.blocks, base.support.blocks, strict=True)):
        assert (a.rigid_mm, a.deformable_mm) == (b.rigid_mm, b.deformable_mm)  # bit for bit, not rounded
    assert (local.support.correction_mm, local.support.sigma_mm) == (base.support.correction_mm,
                                                                    base.support.sigma_mm)
    assert np.array_equal(local.transform(probe), base.transform(probe))


def test_the_load_study_runs_a_method_added_later_alone(tmp_path, monkeypatch):
    """A results file from before ``libr-local``: resuming the study runs that method alone on
    the cases that have the others, every method on a case not begun, and nothing on a
    finished case."""
    from pathlib import Path

    from navapp.evaluation import loads

    old = tmp_path / "loads.csv"
    rows = [{**dict.fromkeys(loads.COLUMNS, ""), "case": case, "level": "S", "method": m}
            for case, methods in (("tool0-a", tuple(m for m in loads.METHODS if m != "libr-local")),
                                  ("tool0-c", loads.METHODS)) for m in methods]
    with loads.ResultsCSV(old, loads.COLUMNS) as out:
        out.write(rows)

    class Case:
        def need_truth(self):
            return None

    asked = []
    monkeypatch.setattr(loads, "read_case", lambda c: Case())
    monkeypatch.setattr(loads, "run_case", lambda c, methods: asked.append((Path(c).name, methods)) or [])
    loads.run_loads([tmp_path / "tool0-a", tmp_path / "tool0-b", tmp_path / "tool0-c"], old)
    assert asked == [("tool0-a", ("libr-local",)), ("tool0-b", loads.METHODS)]


def test_a_warm_start_from_a_fit_with_local_modes_needs_its_own_model(small_model, tool_dent):
    """β of a fit whose model carries local modes has their weights too: a warm start with it
    on the model without them is one clear line, not a shape error deep in LM; on the fit's
    own model it runs."""
    from navapp.errors import InputError
    from navapp.registration.local_modes import LocalModeOptions
    from navapp.registration.pipeline import RobustOptions, register

    data = tool_dent[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reg = register(small_model, data, init=RobustOptions(local_modes=LocalModeOptions()))
        assert reg.local_modes.adopted
        with pytest.raises(InputError, match="pass its own reg.model"):
            register(small_model, data, beta0=reg.libr.beta, rigid=reg.rigid)
        warm = register(reg.model, data, beta0=reg.libr.beta, rigid=reg.rigid)
    assert warm.libr is not None and len(warm.libr.beta) == len(reg.libr.beta)
