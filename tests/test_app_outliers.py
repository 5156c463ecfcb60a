"""A wrong click on an image must not wreck the deformable fit silently: outlier rejection on
every feature keeps the fit with a stray posterior vertex close to the fit without it, the
stray vertex heads the worst-points list, and removing it from there gives the clean data
back. Headless: the App driven through its rooms on a small scene."""

import numpy as np
import pytest
from conftest import BUSY_WAIT_S, start_app, stop_app

from navapp.app.state import RunKind
from navapp.simulation.probe import tracker_to_pixels

SCENE = {"name": "outliers", "anatomy": {"phantom": 0}, "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.2}, "ius": {"planes": 16}}
STRAY_MM = 35.0  # the wrong vertex lies this far below the posterior wall, along the image's depth


@pytest.fixture(scope="module")
def app(cache_root, tmp_path_factory):
    a = start_app(SCENE, cache_root, tmp_path_factory.mktemp("sess"))
    yield a
    stop_app(a)


def register(app, kind=RunKind.ALL):
    assert app.runs.start(kind) is None
    app.core.worker.join(BUSY_WAIT_S)
    assert not app.core.worker.busy
    e = app.core.session.log[-1]
    assert not e.cancelled
    return e


def wall(app):
    """A plane whose posterior wall leaves room for a vertex STRAY_MM below it, and six
    vertices along that wall (image pixels, left to right)."""
    probe = app.core.sd.probe
    room = STRAY_MM / probe.spacing_mm
    for i, plane in sorted(app.core.planes.items()):
        pts = plane.features.get("posterior")
        if pts is None or len(pts) < 40:
            continue
        cols, rows, _ = tracker_to_pixels(probe, plane.probe_to_tracker, pts)
        if rows.max() + room >= probe.height_px - 1:
            continue
        o = np.argsort(cols)
        pick = np.linspace(0, len(o) - 1, 6).round().astype(int)
        return i, [(int(round(cols[o[j]])), int(round(rows[o[j]]))) for j in pick]
    pytest.fail("no plane of the scene shows enough posterior wall")


def believable(app, entry, low=0.5, high=3.0):
    """Issue 50, item 2: every predicted error of the result on show within [low, high] × the true
    one — over the organ (the fit's own check, ``Registration.organ``: 17 mm beside a true 5.0 with
    a stray posterior vertex, as it was made with least-squares weights), at the surface and at
    each tumour."""
    res, reg = app.core.result, app.core.last_reg
    surf = app.core.model.basis.surface
    ratios = {"organ": reg.organ.mean_mm / entry.error_mean_mm,
              "surface": float(res.predicted_mm.mean() / res.node_error_mm[surf].mean())}
    ratios.update({b.name: b.predicted_mm / entry.targets_mm[b.name] for b in res.target_bands})
    assert all(low <= r <= high for r in ratios.values()), ratios
    assert not any("predicted error over the organ" in w.text for w in reg.warnings), reg.warnings


def test_a_stray_vertex_is_rejected_listed_first_and_removable(app):
    app.stylus.collect_now()
    plane, verts = wall(app)
    cs = app.core.new_client_state()
    app.imaging.show(cs, plane)
    for c, r in verts:
        assert app.drawing.click(cs, c, r, "Posterior surface") is None
    assert app.drawing.command(cs, "Finish line") is None
    clean = register(app)
    clean_bands = {b.name: b.predicted_mm for b in app.core.result.target_bands}
    assert not any(w.feature == "posterior" and w.residual_mm > 10 for w in app.core.worst)  # the wall is on it

    # the wrong click: between the first two wall vertices, STRAY_MM deeper than the wall there
    contour = app.core.session.contours[-1]
    c0, r0 = verts[0]
    c1, r1 = verts[1]
    stray = ((c0 + c1) // 2, (r0 + r1) // 2 + int(STRAY_MM / app.core.sd.probe.spacing_mm))
    contour.vertices.insert(1, stray)
    said = []
    notify = app.core.notify
    app.core.notify = lambda title, body, error=False: said.append(body)
    try:
        with_stray = register(app)
    finally:
        app.core.notify = notify
    assert any("left out of the fit" in s for s in said), said  # the surgeon is told, not only the list
    # ... and told how many: the spike's pixels the fit gave no weight, not the listed clicks (it
    # said "1 data point was left out" while the posterior points went from 196 to 417)
    from navapp.app.worker import viewer_options
    from navapp.registration.residuals import point_residuals

    res = point_residuals(app.core.last_reg, viewer_options().weights)
    n_out = sum(p.rejected for p in res)
    assert n_out > 20 and any(f"{n_out:,} of {len(res):,} data points were left out" in s for s in said), \
        (n_out, said)
    # measured: +0.7 mm mean with rejection, +4.4 mm without (5.1 -> 9.5 mm)
    assert with_stray.error_mean_mm <= clean.error_mean_mm + 1.0, (clean, with_stray)
    assert with_stray.error_max_mm <= clean.error_max_mm + 3.0, (clean, with_stray)
    # the predicted error is made with the fit's weights: the rejected spike does not inflate it
    bands = {b.name: b.predicted_mm for b in app.core.result.target_bands}
    assert bands and all(bands[n] <= 1.5 * clean_bands[n] for n in bands), (clean_bands, bands)
    believable(app, with_stray)

    worst = app.core.worst
    assert worst, "the stray vertex is not listed"
    top = worst[0]
    assert top.origin.contour is contour and top.vertex == 1 and top.feature == "posterior"
    assert top.residual_mm > 15 and top.rejected
    assert f"({stray[0]}, {stray[1]})" in top.text()
    assert not any(w.origin.contour is contour and w.vertex != 1 for w in worst)  # the wall's clicks are fine
    # the 2D view rings the stray vertex with its distance
    shown = [c for c in app.view2d_state.view_state(cs.token)["contours"] if c["vertices"][0] == list(verts[0])]
    assert [f["v"] for f in shown[0]["flags"]] == [1] and "mm (not used)" in shown[0]["flags"][0]["text"]

    msg = app.drawing.remove(cs, top)
    assert "Removed the drawn vertex" in msg
    # listed still, in its place and marked removed (``Drawing.remove``: the list is not renumbered)
    assert contour.vertices == verts and top is app.core.worst[0] and app.drawing.gone(top)
    assert app.drawing.command(cs, "Undo") is None  # the removal is undoable
    assert contour.vertices[1] == stray and not app.drawing.gone(top)
    app.drawing.remove(cs, top)
    assert contour.vertices == verts


def test_point_residuals_name_every_point(small_model):
    from navapp.registration.objective import Rejection, Weights
    from navapp.registration.pipeline import register as fit
    from navapp.registration.residuals import point_residuals

    surf = small_model.features["liver"].rest
    rng = np.random.default_rng(0)
    pts = surf[rng.choice(len(surf), 60, replace=False)]
    centre = surf.mean(0)
    far = pts[0] + 40.0 * (pts[0] - centre) / np.linalg.norm(pts[0] - centre)  # 40 mm outside the liver
    data = {"anterior": np.vstack([pts, far])}
    w = Weights(reject=Rejection())
    from navapp.registration.libr import LMOptions

    reg = fit(small_model, data, deform=False, options=LMOptions(weights=w))
    res = point_residuals(reg, w)
    assert len(res) == 61 and {(p.feature, p.index) for p in res} == {("anterior", i) for i in range(61)}
    assert res[0].index == 60 and res[0].residual_mm > 12 and res[0].rejected
    assert not any(p.rejected for p in res[1:])
    assert all(a.residual_mm >= b.residual_mm for a, b in zip(res, res[1:], strict=False))


def ring(app, plane, feature, n=8):
    """``n`` vertices around the lumen of ``feature`` (a vessel contour) on ``plane``, as a
    surgeon clicks them: the simulated contour's pixels nearest n equally spaced angles."""
    probe = app.core.sd.probe
    cols, rows, _ = tracker_to_pixels(probe, app.core.planes[plane].probe_to_tracker,
                                      app.core.planes[plane].features[feature])
    ang = np.arctan2(rows - rows.mean(), cols - cols.mean())
    out = []
    for a in np.linspace(-np.pi, np.pi, n, endpoint=False):
        j = int(np.argmin(np.abs(np.angle(np.exp(1j * (ang - a))))))
        out.append((int(round(cols[j])), int(round(rows[j]))))
    return out


def vessel_plane(app):
    """A plane showing one compact portal and one compact hepatic lumen."""
    probe = app.core.sd.probe
    for i, plane in sorted(app.core.planes.items()):
        ok = True
        for f in ("portal_contour", "hepatic_contour"):
            pts = plane.features.get(f)
            if pts is None or not 40 <= len(pts) <= 200:
                ok = False
                break
            cols, rows, _ = tracker_to_pixels(probe, plane.probe_to_tracker, pts)
            ok = ok and np.ptp(cols) < 80 and np.ptp(rows) < 80 and rows.min() > STRAY_MM / probe.spacing_mm + 5
        if ok:
            return i
    pytest.fail("no plane of the scene shows a portal and a hepatic lumen")


def test_a_stray_vessel_contour_vertex_is_left_out_and_listed(app):
    """A closed PV or HV contour with one vertex STRAY_MM off its lumen: the vertex is left out
    before the fit (a vessel tree has a branch near most places, so its spike's residuals stay
    under the cut: the portal case dragged the fit 5.3 -> 9.3 mm mean without this), listed
    first as not used, and the surgeon is told."""
    app.stylus.collect_now()
    plane = vessel_plane(app)
    cs = app.core.new_client_state()
    app.imaging.show(cs, plane)
    drawn = {}
    for words, feature in (("PV contour", "portal_contour"), ("HV contour", "hepatic_contour")):
        for c, r in ring(app, plane, feature):
            assert app.drawing.click(cs, c, r, words) is None
        assert app.drawing.command(cs, "Close") is None
        drawn[feature] = app.core.session.contours[-1]
    clean = register(app)
    assert not any(w.origin.contour in drawn.values() for w in app.core.worst)
    step = int(STRAY_MM / app.core.sd.probe.spacing_mm)
    for feature, contour in drawn.items():
        good = contour.vertices[2]
        stray = (good[0], good[1] - step)  # towards the probe, off the lumen
        contour.vertices[2] = stray
        said = []
        notify = app.core.notify
        app.core.notify = lambda title, body, error=False, said=said: said.append(body)
        try:
            with_stray = register(app)
        finally:
            app.core.notify = notify
        contour.vertices[2] = good
        assert with_stray.error_mean_mm <= clean.error_mean_mm + 1.0, (feature, clean, with_stray)
        assert with_stray.error_max_mm <= clean.error_max_mm + 3.0, (feature, clean, with_stray)
        top = app.core.worst[0]
        assert top.origin.contour is contour and top.vertex == 2 and top.rejected, (feature, app.core.worst)
        assert top.residual_mm > 15 and f"({stray[0]}, {stray[1]})" in top.text()
        assert not any(w.origin.contour is contour and w.vertex != 2 for w in app.core.worst)
        assert any("left out of the fit" in s for s in said), said
        believable(app, with_stray)
