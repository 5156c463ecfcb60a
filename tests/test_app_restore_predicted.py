"""After a server restart the predicted error comes from the data the restored fit was made
from, not from whatever the session holds now: a plane's segmentation added after the last
registration must not change the numbers the viewer shows nor the ones "Suggest the next
plane" compares them with (it inflated the reduced χ² of the LM covariance: a restarted
demo's panel read an organ mean of 113.63 mm beside targets at 2.8 and 5.2 mm)."""

import json

import numpy as np
import pytest
from conftest import BUSY_WAIT_S, start_app, stop_app

from navapp.app.state import RunKind
from tests.test_app_server import SCENE


def test_restored_fit_keeps_its_own_data_for_the_predicted_error(cache_root, tmp_path):
    from navapp.app.worker import viewer_options
    from navapp.registration.next_plane import suggest_planes
    from navapp.registration.uncertainty import estimate_error

    app = start_app(SCENE, cache_root, tmp_path / "session")
    try:
        app.stylus.collect_now()
        assert app.runs.start(RunKind.SURFACE) is None
        app.core.worker.join(BUSY_WAIT_S)
        reg = app.core.last_reg
        assert reg is not None and reg.deformed
        fitted = {k: v.copy() for k, v in reg.data_model_frame.items()}
        before = suggest_planes(reg, preop=app.core.preop).current_mean_mm
        cs = app.core.new_client_state()
        plane = next(i for i in sorted(app.core.planes) if app.core.planes[i].features)
        app.imaging.show(cs, plane)
        assert app.imaging.add(cs) is None  # data the surface fit never saw, not registered yet
        assert set(app.core.data()) > set(fitted)
    finally:
        stop_app(app)

    again = start_app(SCENE, cache_root, tmp_path / "session")
    try:
        reg = again.core.last_reg
        assert reg is not None and reg.libr is not None
        # the organ mean the suggestion starts from is the one before the restart
        assert suggest_planes(reg, preop=again.core.preop).current_mean_mm == pytest.approx(before, abs=0.01)
        assert set(reg.data_model_frame) == set(fitted)
        for name, pts in fitted.items():
            assert np.allclose(reg.data_model_frame[name], pts, atol=1e-3)
        # and the targets' bands on show are what the restored fit predicts (with the viewer's weights)
        est = estimate_error(reg, points=np.array([t.centre for t in again.core.preop.targets]),
                             weights=viewer_options().weights)
        shown = [b.predicted_mm for b in again.core.result.target_bands]
        assert np.allclose(est.predicted_mm, shown, atol=0.01)
    finally:
        stop_app(again)

    # a session saved before the fit's data were kept: its prediction is shown as saved, and
    # the suggestion asks for a registration instead of ranking planes on other data
    path = tmp_path / "session" / "session.json"
    saved = json.loads(path.read_text())
    del saved["result"]["data_model_frame"]
    path.write_text(json.dumps(saved))
    old = start_app(SCENE, cache_root, tmp_path / "session")
    try:
        assert [b.predicted_mm for b in old.core.result.target_bands] == pytest.approx(shown)
        assert "Register deformably first" in old.imaging.suggest(old.core.new_client_state(), print)
    finally:
        stop_app(old)
