"""The showing side of a tracked data source, one home (``navapp.app.sources``): found from
``features.TABLE`` as the receiving side is, one shown source per receiver, in its order; a
point source's points handed to the session once each, the stylus's tip taken off the views
and bannered when the watchdog loses it. The viewer's whole live path is walked in
test_app_live.py; these check the rooms alone, without a server."""

from types import SimpleNamespace

import numpy as np

from navapp.app.sources import PointsShown, Wiring, build
from navapp.app.sources.ius import ProbeShown
from navapp.app.sources.stylus import StylusShown
from navapp.app.state import Change
from navapp.tracking.client import TrackingClient
from navapp.tracking.config import TrackingConfig
from navapp.tracking.events import SourcePoints, StylusSample, ToolStatus
from navapp.tracking.receivers import Shared
from navapp.tracking.receivers import build as build_receivers
from navapp.tracking.receivers.points import PointsSettings
from navapp.tracking.receivers.stylus import StylusSettings


class Views:
    """A stand-in for ``Core``: records what each view was asked to do."""

    def __init__(self):
        self.calls = []

    def each_view(self, fn):
        view = SimpleNamespace(show_live_tip=lambda tip: self.calls.append(("tip", tip)),
                               show_live_frame=lambda f: self.calls.append(("frame", f)),
                               refresh=lambda what: self.calls.append(("refresh", what)))
        fn(view)


def _wiring(client, config=None, frames=None):
    return Wiring(client, config or TrackingConfig(), Views(), lambda: frames.append(1) if frames is not None else None)


def test_each_received_source_is_shown_by_one_room_found_from_the_feature_table():
    cfg = TrackingConfig(tools=(PointsSettings("laparoscope", "CameraToReference"),))
    client = TrackingClient(cfg)  # not started: nothing connects
    shown = build(_wiring(client, cfg))
    assert [s.source for s in shown] == [r.source for r in build_receivers(cfg.tools, Shared(client.digitiser))] \
        == ["stylus", "ius", "laparoscope"]
    assert [type(s) for s in shown] == [StylusShown, ProbeShown, PointsShown]


def test_a_point_source_hands_on_its_own_points_once_each_in_order():
    lap = PointsShown("laparoscope", _wiring(None))
    a, b = np.arange(6.0).reshape(2, 3), np.arange(9.0).reshape(3, 3) + 100
    assert lap.wakes(SourcePoints(1.0, 1.0, "laparoscope", a))
    assert not lap.wakes(SourcePoints(1.5, 1.5, "another_source", a))  # not its feature
    assert not lap.wakes(StylusSample(1.6, 1.6, np.zeros(3), np.eye(4)))
    assert lap.wakes(SourcePoints(2.0, 2.0, "laparoscope", b))
    got = lap.taken()
    assert [labels for _, labels in got] == [["laparoscope"] * 2, ["laparoscope"] * 3]
    assert np.array_equal(np.vstack([p for p, _ in got]), np.vstack([a, b]))
    assert lap.taken() == []  # each point once


class Stylus:
    """A stand-in for the client as the stylus reads it: its latest sample, whether the
    watchdog calls it seen, and its digitiser's points."""

    def __init__(self):
        self.latest_stylus = None
        self.seen = True
        self.digitiser = SimpleNamespace(points=lambda: self.points, labels=lambda: self.labels, recording=False)
        self.points, self.labels = np.zeros((0, 3)), []

    def fresh(self, source, status):
        assert source == "stylus"
        return self.seen


def test_a_lost_stylus_is_taken_off_the_views_and_bannered_and_its_digitised_points_taken_once():
    client = Stylus()
    cfg = TrackingConfig()
    device = cfg.tool("stylus", StylusSettings).device
    stylus = StylusShown(_wiring(client, cfg))
    views = stylus.core
    seen = {device: ToolStatus(device, "seen", 0.01)}
    client.latest_stylus = StylusSample(1.0, 1.0, np.array([1.0, 2.0, 3.0]), np.eye(4))
    assert not stylus.show(10.0, seen)
    assert np.array_equal(stylus.tip, [1, 2, 3]) and stylus.lost is None and views.calls[-1][0] == "tip"
    stylus.show(10.001, seen)  # the same sample: not sent again
    assert len(views.calls) == 1
    client.seen = False
    stale = {device: ToolStatus(device, "stale", 0.3)}
    assert stylus.show(10.5, stale)  # lost now: the panels refresh at once
    assert stylus.tip is None and "not tracked" in stylus.lost and "0.3 s ago" in stylus.lost
    assert views.calls[1:] == [("tip", None), ("refresh", Change.LIVE)]
    assert not stylus.show(10.6, stale)  # nothing new to say
    missing = {device: ToolStatus(device, "missing", 1.2)}
    assert stylus.show(11.5, missing)  # stale → missing: at once, not at the next periodic refresh
    stylus.age(missing)
    assert stylus.lost.startswith("Stylus lost") and "1.2 s ago" in stylus.lost
    client.seen = True
    client.latest_stylus = StylusSample(12.0, 12.0, np.array([4.0, 5.0, 6.0]), np.eye(4))
    stylus.show(12.0, seen)
    assert stylus.lost is None and np.array_equal(stylus.tip, [4, 5, 6])
    client.points, client.labels = np.ones((3, 3)), ["anterior"] * 3
    got = stylus.taken()
    assert len(got) == 1 and len(got[0][0]) == 3 and got[0][1] == ["anterior"] * 3
    assert stylus.taken() == []
    client.points, client.labels = np.ones((5, 3)), ["anterior"] * 3 + ["falciform"] * 2
    assert [labels for _, labels in stylus.taken()] == [["falciform"] * 2]
