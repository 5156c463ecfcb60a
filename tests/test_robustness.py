"""Registration robust to the starting pose and to imprecise labels, and a warning when
the fit is poor. Everything runs on the 12 mm phantom-0 model (k = 12);
the study itself (``navapp study robustness``) runs on the nine simulated cases."""

import json

import numpy as np
import pytest
import trimesh

from navapp.evaluation.robustness import mislabel, offset_transform, shift_labels
from navapp.geometry.tre import mean_tre
from navapp.registration.pipeline import RobustOptions, deform_points, register
from navapp.registration.quality import assess_fit
from navapp.registration.rigid import multi_start_icp, start_poses
from navapp.registration.rotation import rotation


def phantom_case(model, seed=0, noise_mm=0.5):
    """Sparse data of a deformed phantom-0 and the true positions of every mesh node.

    Stylus-like data: a patch of the anterior surface (outward normal toward +y, one
    side of the falciform), the falciform and ridge regions, and one iUS-like slab of
    the portal vein surface; all deformed by a state of the basis and noised by
    ``noise_mm``. Returns (data, truth nodes (M, 3) mm)."""
    rng = np.random.default_rng(seed)
    n = model.basis.Ju.shape[1]
    alpha = rng.normal(size=n) * 0.8
    beta = np.concatenate([alpha, [2.0, -1.0, 1.5], np.radians([2.0, -1.5, 1.0])])

    def deformed(name):
        return deform_points(model.basis, model.centroid, beta, model.features[name].rest)

    rest = model.features["liver"].rest
    liver = trimesh.Trimesh(rest, model.features["liver"].cells, process=False)
    ant = (liver.vertex_normals[:, 1] > 0.3) & (rest[:, 0] < np.median(rest[:, 0]))
    portal = model.features["portal"].rest
    slab = np.abs(portal[:, 2] - np.median(portal[:, 2])) < 3.0
    data = {"anterior": deformed("liver")[ant]}
    for name in ("falciform", "ridge_left", "ridge_right"):
        if name in model.features:
            data[name] = deformed(name)
    data["portal_contour"] = deformed("portal")[slab]
    data = {k: v + rng.normal(size=v.shape) * noise_mm for k, v in data.items()}
    truth = deform_points(model.basis, model.centroid, beta, model.basis.nodes)
    return data, truth


def tre_after(model, data, truth, **kw):
    reg = register(model, data, **kw)
    return mean_tre(reg.transform(model.basis.nodes), truth), reg


def test_fifteen_degrees_thirty_mm_offset_within_ten_percent(small_model):
    data, truth = phantom_case(small_model)
    ref, _ = tre_after(small_model, data, truth)
    pivot = np.vstack(list(data.values())).mean(0)
    for seed in range(3):  # three random axes and directions
        move = offset_transform(np.random.default_rng(seed), 15.0, 30.0, pivot)
        tre, _ = tre_after(small_model, {k: move(v) for k, v in data.items()}, move(truth))
        assert tre <= 1.1 * ref, (seed, tre, ref)


def test_multi_start_icp_recovers_a_25_degree_pose(small_model):
    """Undeformed data turned 25° and shifted 20 mm: the starts (tracker, ±15° about each
    axis, principal axes) converge, and the best basin is the true pose to within the
    vertex matching of this 12 mm mesh."""
    rest = small_model.features["liver"].rest
    data = {"anterior": rest[rest[:, 1] > np.percentile(rest[:, 1], 60)]}
    for name in ("falciform", "ridge_left", "ridge_right"):
        data[name] = small_model.features[name].rest
    c = small_model.centroid
    R, t = rotation(np.radians([0.0, 10.0, 25.0])), np.array([12.0, -10.0, 12.0])
    moved = {k: (v - c) @ R.T + c + t for k, v in data.items()}
    starts = multi_start_icp(small_model, moved, start_poses(small_model, moved))
    assert len(starts) == 8 and {s.label for s in starts} >= {"tracker", "rx+15", "rz-15", "principal-axes"}
    best = min(starts, key=lambda s: s.result.rms_mm)
    angle = np.degrees(np.arccos(np.clip((np.trace(best.result.R @ R.T) - 1) / 2, -1, 1)))
    placed = best.result.apply(small_model.basis.nodes)
    assert angle < 2.0 and np.linalg.norm(placed - ((small_model.basis.nodes - c) @ R.T + c + t), axis=1).mean() < 2.0


def test_shifted_salient_labels_raise_tre_by_less_than_2_5_mm(small_model):
    """Falciform and ridge points slid 5–10 mm along the true surface (the study's
    ``shifted`` condition): the default fit (Huber δ = 1 mm on these features) loses less
    than 2.5 mm of mean TRE, and less than plain least squares does. Here the salient
    data are the whole labelled regions, a harder case than the study's stylus crossings."""
    data, truth = phantom_case(small_model, seed=2)
    local = np.full(small_model.basis.M, -1)
    local[small_model.basis.surface] = np.arange(len(small_model.basis.surface))
    surface = trimesh.Trimesh(truth[small_model.basis.surface], local[small_model.basis.surface_faces],
                              process=False)
    least_squares = RobustOptions(huber_salient_mm=None)
    clean, _ = tre_after(small_model, data, truth)
    clean_ls, _ = tre_after(small_model, data, truth, init=least_squares)
    cost, cost_ls = [], []
    for seed in range(2):
        shifted = shift_labels(data, surface, np.random.default_rng(seed))
        assert np.linalg.norm(shifted["ridge_left"] - data["ridge_left"], axis=1).mean() > 3.0  # really moved
        cost.append(tre_after(small_model, shifted, truth)[0] - clean)
        cost_ls.append(tre_after(small_model, shifted, truth, init=least_squares)[0] - clean_ls)
    assert max(cost) < 2.5 and np.mean(cost) < np.mean(cost_ls), (cost, cost_ls)


def test_mislabel_swaps_ten_percent_with_nearby_anterior_points():
    rng = np.random.default_rng(0)
    data = {"anterior": rng.normal(size=(200, 3)) * 30, "ridge_left": rng.normal(size=(40, 3)) * 5 + 40}
    out = mislabel(data, np.random.default_rng(1))
    assert len(out["ridge_left"]) == 40 and len(out["anterior"]) == 200
    kept = (out["ridge_left"][:, None] == data["ridge_left"][None]).all(-1).any(1)
    assert kept.sum() == 36


def test_poor_fit_warning_fires_on_another_liver_and_not_on_its_own(small_model, phantoms):
    own, _ = phantom_case(small_model, seed=3)
    reg = register(small_model, own)
    assert reg.quality is not None and reg.quality.ok and reg.quality.warning is None
    # data from phantom 1: no state of phantom 0's basis can reach it
    other = phantoms[1]
    v, nrm = other.liver.vertices, other.liver.vertex_normals
    data = {"anterior": v[(nrm[:, 1] > 0.3)][::4]}
    for name in ("falciform", "ridge_left", "ridge_right"):
        if other.region_mask(name).any():
            data[name] = v[other.region_mask(name)][::2]
    bad = register(small_model, data)
    assert not bad.quality.ok, bad.quality.as_dict()
    line = bad.quality.warning
    assert "\n" not in line and line.startswith("poor fit:") and bad.quality.flagged[0] in line


def test_fit_quality_thresholds():
    q = assess_fit({"anterior": {"n": 100, "rms_mm": 2.6}, "falciform": {"n": 100, "rms_mm": 3.0},
                    "ridge_left": {"n": 3, "rms_mm": 9.0}, "strain_energy": {"f_E_pa": 1.0}})
    assert q.flagged == ["anterior"]  # 0.5 + 2 mm allowed; salient 1.5 + 2; 3 points are too few
    assert assess_fit({"anterior": {"n": 100, "rms_mm": 2.6}}, noise_mm={"anterior": 1.0}).ok


def test_single_icp_options_are_one_plain_icp_then_libr(small_model):
    """``RobustOptions.single_icp()`` (the study's "single-icp" rows) is one exact
    point-to-point ICP from the given pose, then plain LIBR: no starts, no guards."""
    from navapp.registration.libr import register_libr
    from navapp.registration.rigid import TOL_BEFORE_LIBR, rigid_icp

    data, _ = phantom_case(small_model, seed=4)
    reg = register(small_model, data, init=RobustOptions.single_icp())
    rigid = rigid_icp(small_model, data, tol_mm=TOL_BEFORE_LIBR, multi_start=False, robust=None)
    libr = register_libr(small_model, {k: rigid.inverse(v) for k, v in data.items()})
    assert not reg.starts and np.array_equal(reg.rigid.R, rigid.R) and np.array_equal(reg.libr.beta, libr.beta)


def test_huber_weights_are_held_within_an_iteration(small_model):
    """With Huber δ on a feature, an evaluation at held correspondences and held scales is
    one weighted least-squares problem: Ω there equals Σ w·s·f² with the held scales."""
    from navapp.registration.objective import Weights, evaluate

    data, _ = phantom_case(small_model, seed=5)
    data["ridge_left"] = data["ridge_left"] + 6.0  # far off: Huber must down-weight them
    n = small_model.basis.Ju.shape[1]
    w = Weights(huber_mm={"ridge_left": 2.0})
    ev = evaluate(small_model, data, np.zeros(n + 6), w)
    assert ev.scales["ridge_left"].min() < 0.5
    step = np.concatenate([np.zeros(n), [0.3, 0.0, 0.0], [0.0, 0.0, 0.0]])
    held = evaluate(small_model, data, step, w, jacobian=False, frozen=ev.correspondence, scales=ev.scales)
    assert np.array_equal(held.w, ev.w) and np.isclose(held.omega, float(held.w @ held.f ** 2))


@pytest.mark.parametrize("flag", [False, True])
def test_cli_prints_one_warning_line_and_result_json_keeps_it(tmp_path, capsys, flag):
    from navapp.cli import main
    from tests.test_register_cli import make_case

    make_case(tmp_path / "c")
    if flag:  # stylus data of a much flatter organ: unreachable for this liver
        p = np.loadtxt(tmp_path / "c/intraop/anterior.csv", delimiter=",", skiprows=1)
        p[:, 1] = 20 + 0.3 * (p[:, 1] - 20) + 0.004 * p[:, 0] ** 2
        (tmp_path / "c/intraop/anterior.csv").write_text(
            "x,y,z\n" + "\n".join(",".join(repr(float(x)) for x in r) for r in p) + "\n")
    assert main(["--quiet", "register", str(tmp_path / "c"), "--edge", "15", "--k", "10", "--json"]) in (0, None)
    captured = capsys.readouterr()
    result = json.loads((tmp_path / "c/registration/result.json").read_text())
    # the ellipsoid's smooth cap also leaves rotations weakly determined: that is its own
    # line (pose_determinacy), counted apart from the fit-quality warning under test
    lines = [ln for ln in captured.err.splitlines() if "warning" in ln]
    pose = [ln for ln in lines if "the pose is not determined" in ln]
    warnings = [ln for ln in lines if ln not in pose]
    assert len(pose) <= 1 and (not pose or result["pose_determinacy"]["warning"] in pose[0])
    assert result["fit_quality"]["residuals_ok"] is (not flag)
    assert result["ok"] is result["fit_quality"]["ok"] is (not result["warnings"])  # one rule
    if flag:
        # the fit-quality line once; data of another organ are not predicted by the
        # deformation either, which is its own line (support)
        poor = [ln for ln in warnings if "poor fit" in ln]
        assert len(poor) == 1 and "anterior" in poor[0]
        # and where ICP's move is not earned by a better fit, the given pose is kept with its own line
        assert all("poor fit" in ln or "deformation not supported by the data" in ln
                   or "deformation not determined by the data" in ln
                   or "ICP's pose is not earned by the fit" in ln for ln in warnings)
        assert result["fit_quality"]["warning"] in json.loads(captured.out.strip().splitlines()[-1])["warning"]
    else:
        assert warnings == [] and result["fit_quality"]["warning"] is None


def test_rigid_icp_discounts_a_mislabelled_stretch(small_model):
    """10 % of each salient feature's points swapped for anterior points 10–40 mm away (the
    study's ``mislabelled`` condition, made plain): with Huber factors of scale-adaptive δ
    on the salient points (``robust=2``, the default's) the rigid pose stays within a
    fraction of a millimetre of the clean-label pose, where plain weighted ICP is pulled
    away by millimetres; on clean labels the two poses agree."""
    from navapp.registration.rigid import rigid_icp

    nodes = small_model.basis.nodes
    for seed in range(2):
        data, _ = phantom_case(small_model, seed=seed)
        rng = np.random.default_rng(seed)
        bad = dict(data)
        for name in ("falciform", "ridge_left", "ridge_right"):
            m = max(1, len(data[name]) // 10)
            d = np.linalg.norm(data["anterior"][:, None] - data[name][None], axis=2).min(1)
            far = np.flatnonzero((d > 10) & (d < 40))
            if len(far) >= m:
                bad[name] = np.vstack([np.delete(data[name], rng.choice(len(data[name]), m, replace=False), 0),
                                       data["anterior"][rng.choice(far, m, replace=False)]])
        clean = rigid_icp(small_model, data, robust=None).apply(nodes)

        def off(pose, clean=clean):
            return np.linalg.norm(pose.apply(nodes) - clean, axis=1).mean()

        plain, robust = off(rigid_icp(small_model, bad, robust=None)), off(rigid_icp(small_model, bad, robust=2.0))
        assert plain > 1.0 and robust < 0.3 * plain, (seed, plain, robust)
        assert off(rigid_icp(small_model, data, robust=2.0)) < 0.2


def test_default_fit_is_a_continuation_from_a_stiffer_organ(small_model):
    """The default deformable stage fits a stiffer organ (3 × the strain-energy weight)
    first and relaxes to the true weight from there: its answer is another than a fit from
    rest (``stiff_first=None``) after the same rigid stage, with a smoother deformation
    than that fit's or than a continuation from a softer organ (a lower strain energy f_E;
    on seeds 0–4 and 7 it is 1–23 % below the fit from rest's, and on seeds 0, 1 and 7 it
    falls as the first stage gets stiffer, 1/3 → 3 → 10 ×), and its Ω is the true weight's.
    A warm start (β0 given: the last state, e.g. after adding a plane) continues from β0
    without the stiff stage."""
    from navapp.features import SALIENT
    from navapp.registration.libr import LMOptions
    from navapp.registration.objective import Weights, evaluate

    data, _ = phantom_case(small_model, seed=7)
    weights = Weights(huber_mm=dict.fromkeys(SALIENT, RobustOptions().huber_salient_mm))  # as the default
    options = LMOptions(weights=weights)
    cont = register(small_model, data, options=options, init=RobustOptions(retry_poor_fit=False))
    plain = register(small_model, data, options=options, init=RobustOptions(retry_poor_fit=False, stiff_first=None))
    assert np.array_equal(cont.rigid.R, plain.rigid.R) and np.array_equal(cont.rigid.t, plain.rigid.t)
    assert np.abs(cont.libr.beta - plain.libr.beta).max() > 0.1
    softer = register(small_model, data, options=options, init=RobustOptions(retry_poor_fit=False, stiff_first=1 / 3))
    energy = {name: reg.libr.features["strain_energy"]["f_E_pa"]
              for name, reg in (("cont", cont), ("plain", plain), ("softer", softer))}
    assert energy["cont"] < 0.9 * min(energy["plain"], energy["softer"]), energy
    true_omega = evaluate(small_model, cont.data_model_frame, cont.libr.beta, weights, jacobian=False).omega
    assert np.isclose(cont.libr.omega, true_omega, rtol=1e-9, atol=0)
    warm = [register(small_model, data, options=options, rigid=cont.rigid, beta0=plain.libr.beta,
                     init=RobustOptions(retry_poor_fit=False, stiff_first=s)).libr.beta for s in (3.0, None)]
    assert np.array_equal(warm[0], warm[1])


def test_the_committed_rows_name_methods_that_exist():
    """The committed study rows are reported under today's method names: a method renamed
    in ``METHODS`` without rewriting the rows (as notes/scripts/rename_robustness_methods.py did once) would
    drop them from the regenerated report's comparisons."""
    from pathlib import Path

    from navapp.evaluation.robustness import BASELINE, DEFAULT, read_rows
    from navapp.registration.pipeline import METHODS

    names = {r["method"] for r in read_rows(Path(__file__).parents[1] / "results" / "robustness.csv")}
    assert {BASELINE, DEFAULT} <= names <= set(METHODS)
    assert all(isinstance(make(), RobustOptions) for make in METHODS.values())
