"""The next best ultrasound plane."""

import numpy as np
import pytest
import trimesh

from navapp.defaults import PROBE_SPACING_MM
from navapp.geometry.transforms import probe_pose
from navapp.registration.libr import register_libr
from navapp.registration.next_plane import (
    _extra_blocks,
    anterior_surface_mask,
    expected_features,
    suggest_planes,
)
from navapp.registration.pipeline import Registration
from navapp.registration.rigid import RigidResult
from navapp.registration.uncertainty import default_weights, information


def _registration(model, data):
    return Registration(model, RigidResult(np.eye(3), np.zeros(3), 0, 0.0), register_libr(model, data), data)


def _anterior_data(model, rng, keep):
    """A small deformation and anterior points where ``keep(X)`` holds."""
    n = model.basis.Ju.shape[1]
    beta = np.concatenate([rng.normal(size=n) * 0.3, np.zeros(6)])
    _, X = model.positions(model.features["liver"], beta)
    up = X[:, 1] > np.median(X[:, 1])
    pts = X[up & keep(X)]
    return {"anterior": pts + rng.normal(size=pts.shape) * 0.3}, beta


def test_suggested_plane_lies_over_the_region_without_data(small_model, phantoms):
    rng = np.random.default_rng(11)
    data, _ = _anterior_data(small_model, rng, lambda X: X[:, 0] < 0)  # nothing over x > 0
    reg = _registration(small_model, data)
    sugg = suggest_planes(reg, preop=phantoms[0], count=6)
    assert len(sugg.candidates) == 12
    scores = [c.score_mm for c in sugg.candidates]
    assert scores == sorted(scores, reverse=True)
    best = sugg.best
    origin = best.pose[:3, 3]
    assert origin[0] > 10.0  # over the half without data
    assert np.linalg.norm(data["anterior"] - origin, axis=1).min() > 15.0
    assert best.features and best.score_mm > 0
    # every candidate over the covered half ranks below it
    covered = [c for c in sugg.candidates if c.pose[0, 3] < -10.0]
    assert covered and all(c.score_mm < best.score_mm for c in covered)
    # and mirrored: with data only over x > 0, the suggestion moves to x < 0
    data2, _ = _anterior_data(small_model, rng, lambda X: X[:, 0] > 0)
    best2 = suggest_planes(_registration(small_model, data2), preop=phantoms[0], count=6).best
    assert best2.pose[0, 3] < -10.0


def _segment_distance(p, seg):
    a, b = seg[:, 0], seg[:, 1]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p[None] - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1)
    return np.linalg.norm(a + t[:, None] * ab - p, axis=1).min()


def test_expected_features_are_the_section_of_the_registered_model(small_model, phantoms):
    """Expected contour points lie on trimesh's plane section of the deformed vessel surface,
    and their pixel count is the section's length inside the image over the pixel size."""
    rng = np.random.default_rng(12)
    n = small_model.basis.Ju.shape[1]
    beta = np.concatenate([rng.normal(size=n) * 0.3, [2.0, -1.0, 0.5], [0.02, -0.01, 0.03]])
    feat = small_model.features["portal"]
    _, X = small_model.positions(feat, beta)
    c = X.mean(0)
    pose = probe_pose(c + np.array([0.0, 40.0, 0.0]), [1.0, 0.0, 0.0], [0.0, -1.0, 0.0])
    feats, pixels = expected_features(small_model, beta, pose)
    assert "portal_contour" in feats
    ref = trimesh.intersections.mesh_plane(trimesh.Trimesh(X, feat.cells, process=False), pose[:3, 1], pose[:3, 3])
    rel = ref - pose[:3, 3]
    u, v = rel @ pose[:3, 0], rel @ pose[:3, 2]
    inside = ((np.abs(u) <= 32.0) & (v >= 0) & (v <= 80.0)).all(1)
    ref = ref[inside]
    pts = feats["portal_contour"]
    assert max(_segment_distance(p, ref) for p in pts) < 1e-6
    length = np.linalg.norm(ref[:, 1] - ref[:, 0], axis=1).sum()
    assert pixels["portal_contour"] == pytest.approx(length / PROBE_SPACING_MM, abs=1.0)
    assert len(pts) == pytest.approx(length, abs=2.0)  # one point per mm


def test_new_plane_information_is_the_registration_s_own_weighting(small_model):
    """H with a plane's points joined (every feature renormalised to w_F / N_F) equals the
    normal matrix of the objective evaluated on the enlarged data."""
    rng = np.random.default_rng(13)
    data, beta = _anterior_data(small_model, rng, lambda X: X[:, 0] < 30)
    _, P = small_model.positions(small_model.features["portal"], beta)
    data["portal_contour"] = P[rng.choice(len(P), 40, replace=False)]
    new = {"portal_contour": P[rng.choice(len(P), 25, replace=False)],
           "posterior": data["anterior"][:10] + 0.1}
    info = information(small_model, data, beta)
    extra = _extra_blocks(small_model, beta, new, {k: len(v) for k, v in new.items()}, default_weights())
    both = dict(data)
    both["portal_contour"] = np.vstack([data["portal_contour"], new["portal_contour"]])
    both["posterior"] = new["posterior"]
    H_ref = information(small_model, both, beta).matrix()
    assert np.allclose(info.matrix(extra), H_ref, rtol=1e-9, atol=1e-12 * np.abs(H_ref).max())


def test_needs_a_deformable_registration(small_model):
    reg = Registration(small_model, RigidResult(np.eye(3), np.zeros(3), 0, 0.0), None, {})
    with pytest.raises(ValueError, match="deformable"):
        suggest_planes(reg)


def test_anterior_mask_follows_the_labels(small_model, phantoms):
    m = anterior_surface_mask(small_model, phantoms[0])
    assert m.shape == (len(small_model.features["liver"].rest),) and 0 < m.sum() < len(m)


def test_table2_section_summarises_the_two_studies(tmp_path):
    import csv

    from navapp.evaluation.next_plane_study import table2_section

    with (tmp_path / "error_estimate.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, ("set", "level", "r_pred", "coverage"))
        w.writeheader()
        for lv, r in (("S", 0.6), ("CBCT", 0.2), ("all", 0.5)):
            w.writerow({"set": "validation cases", "level": lv, "r_pred": r, "coverage": 0.9})
    with (tmp_path / "next_plane.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, ("set", "criterion", "level", "tre_mean_mm", "tre_table2_mm", "rank", "combinations",
                               "level_mean_mm"))
        w.writeheader()
        for case_rank, tre in ((2, 3.0), (6, 4.0)):
            w.writerow({"set": "study cases", "criterion": "ê (default)", "level": "S+1", "tre_mean_mm": tre,
                        "tre_table2_mm": tre, "rank": case_rank, "combinations": 16, "level_mean_mm": 3.5})
    text = table2_section(tmp_path)
    assert "| r | 0.60 | 0.20 |" in text and "| coverage | 90% | 90% |" in text
    assert "| S + 1 suggested | 3.50 | 3.50 | 4 of 16 | 1 of 2 cases |" in text


def test_planes_are_ranked_by_the_targets_when_given(small_model, phantoms):
    """With target points (the viewer passes the tumours' centres) the predicted error is
    compared there, not over the organ: a target inside one candidate's image makes that plane
    (or one through the same spot) the best, where the organ-wide ranking put it last."""
    rng = np.random.default_rng(11)
    data, _ = _anterior_data(small_model, rng, lambda X: X[:, 0] < 0)
    reg = _registration(small_model, data)
    organ = suggest_planes(reg, preop=phantoms[0], count=6)
    last = [c for c in organ.candidates if c.features][-1]
    target = np.vstack(list(last.features.values())).mean(0)  # the middle of what its image shows

    def plane_distance(c):
        return abs(float(c.pose[:3, 1] @ (target - c.pose[:3, 3])))

    by_target = suggest_planes(reg, preop=phantoms[0], count=6, points=target[None], points_name="tumour 1")
    assert by_target.over == "tumour 1" and organ.over.startswith("the whole organ")
    assert by_target.best.index != organ.best.index
    assert plane_distance(by_target.best) < 5.0 < plane_distance(organ.best)
    assert by_target.best.score_mm > 0
