"""The receiving side of a tracked data source, one home (``navapp.tracking.receivers``):
the registry finds each source's receiver from ``features.TABLE``; a tracked laparoscope's
depth points, sent in its camera frame, arrive in Reference placed by its own TRANSFORM —
with no code of its own in ``tracking`` or the viewer, only its ``[tools.laparoscope]``."""

import socket
import time

import numpy as np
import pyigtl
import pytest
from conftest import refused_in_one_line, wait_until
from scipy.spatial.transform import Rotation

from navapp.tracking.client import TrackingClient
from navapp.tracking.config import TrackingConfig, load_config
from navapp.tracking.digitiser import Digitiser
from navapp.tracking.events import Skipped, SourcePoints, TransformSample
from navapp.tracking.receivers import PointsReceiver, Shared, build
from navapp.tracking.receivers.ius import ProbeReceiver, ProbeSettings
from navapp.tracking.receivers.points import PointsSettings
from navapp.tracking.receivers.stylus import StylusReceiver, StylusSettings

POSE = "CameraToReference"


def _camera_to_reference():
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", [30.0, -50.0, 110.0], degrees=True).as_matrix()
    m[:3, 3] = [-40.0, 125.5, 310.0]
    return m


def test_each_source_has_one_receiver_found_from_the_feature_table():
    cfg = TrackingConfig(tools=(ProbeSettings(image_pose="calibration"), PointsSettings("laparoscope", POSE)))
    got = build(cfg.tools, Shared(Digitiser(), cfg.stale_s))
    assert [r.source for r in got] == ["stylus", "ius", "laparoscope"]  # fiducials: not received
    stylus, ius, lap = got
    assert isinstance(stylus, StylusReceiver) and isinstance(ius, ProbeReceiver) and isinstance(lap, PointsReceiver)
    assert (lap.features, lap.pose, lap.max_pose_age_s) == (("laparoscope",), POSE, cfg.stale_s)
    # the watchdog's devices, in the order the viewer lists them: as before receivers, then the tool's pose
    client = TrackingClient(cfg)
    names = [stylus.device, ius.probe, ius.image]
    assert names == ["StylusTipToReference", "ProbeToReference", "Image_Reference"] and ius.image_pose == "calibration"
    assert list(client.status()) == [*names, POSE]
    assert list(TrackingClient(TrackingConfig()).status()) == names


def test_tools_in_the_config_are_read_and_bad_ones_refused_in_one_line(tmp_path):
    good = tmp_path / "tracking.toml"
    good.write_text(f'[tools.laparoscope]\npose = "{POSE}"\n')
    cfg = load_config(good)
    assert cfg.tool("laparoscope", PointsSettings) == PointsSettings("laparoscope", POSE)
    assert cfg.tool("stylus", StylusSettings) == StylusSettings()  # the others: their defaults
    assert TrackingConfig().tool("laparoscope", PointsSettings).pose is None
    for text, problem in [('[tools.stylus]\npose = "X"\n', "unknown tool [tools.stylus] (known: laparoscope)"),
                          ('[tools.laparoscope]\nposes = "X"\n', "unknown key tools.laparoscope.poses"),
                          ('[tools.laparoscope]\n', "tools.laparoscope.pose is missing"),
                          ('[tools.laparoscope]\npose = 3\n', "tools.laparoscope.pose must be a str"),
                          ('[tools.laparoscope]\npose = "ProbeToReference"\n', "another device's name"),
                          ('[tools.laparoscope]\npose = "ALaparoscopeCameraToReference"\n', "1–20 bytes"),
                          ('[tools]\nlaparoscope = 1\n', "[tools.laparoscope] must be a table")]:
        refused_in_one_line(load_config, tmp_path / "bad.toml", text, problem)


def test_a_tracked_laparoscopes_camera_points_arrive_in_reference_placed_by_its_pose():
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(5.0)
    events: list = []
    cfg = TrackingConfig(port=listener.getsockname()[1], reconnect_s=0.05, tools=(PointsSettings("laparoscope", POSE),))
    client = TrackingClient(cfg, on_event=events.append).start()
    in_camera = np.array([[1.0, -2.0, 95.0], [4.0, 5.0, 110.5], [-7.0, 8.0, 130.25]])
    pose = _camera_to_reference()
    moved = pose.copy()
    moved[:3, 3] += [5.0, 0.0, -3.0]
    try:
        conn, _ = listener.accept()
        t = time.time()

        def points(stamp, positions=in_camera):
            return pyigtl.PointMessage(positions=positions, device_name="laparoscope", timestamp=stamp).pack()

        def transform(m, stamp):
            return pyigtl.TransformMessage(m, timestamp=stamp, device_name=POSE).pack()

        conn.sendall(points(t)  # before any pose: not placed, refused
                     + transform(pose, t + 0.05) + points(t + 0.1)  # placed by the pose 0.05 s before
                     + transform(moved, t + 0.2) + points(t + 0.6)  # the pose 0.4 s old (stale_s 0.2): refused
                     + transform(moved, t + 0.7) + points(t + 0.7, in_camera[:1]))
        wait_until(lambda: sum(isinstance(e, SourcePoints) for e in events) >= 2)
    finally:
        client.stop()
        listener.close()
    got = [e for e in events if isinstance(e, SourcePoints)]
    assert [e.feature for e in got] == ["laparoscope", "laparoscope"]
    # float32 on the wire (OpenIGTLink's TRANSFORM and POINT): placed as received, to 1e-4 mm
    expected = in_camera @ pose[:3, :3].T + pose[:3, 3]
    np.testing.assert_allclose(got[0].points, expected, atol=1e-4)
    np.testing.assert_allclose(got[1].points, in_camera[:1] @ moved[:3, :3].T + moved[:3, 3], atol=1e-4)
    assert np.abs(got[0].points - in_camera).max() > 50.0  # not passed through in the camera's frame
    skipped = [e for e in events if isinstance(e, Skipped)]
    assert [e.kind for e in skipped] == ["malformed", "malformed"]
    assert f"no {POSE} yet" in skipped[0].detail and "0.40 s from the points" in skipped[1].detail
    assert sum(isinstance(e, TransformSample) and e.name == POSE for e in events) == 3
    assert client.counts["POINT"] == 2
    conn.close()


def test_the_viewer_takes_a_tracked_laparoscopes_points_into_its_session_in_reference(cache_root, tmp_path):
    """``navapp serve --igtl`` with ``[tools.laparoscope]``: the camera-frame points join the
    session's data placed by the camera's pose, through the same path as untracked ones."""
    from conftest import free_port
    from test_laparoscope import SCENE

    from navapp.app.server import App
    from navapp.simulation.scene import parse_scene
    from navapp.tracking.replay import quiet_server

    server = quiet_server(0)
    server.start()
    cfg = TrackingConfig(port=server.server_address[1], tools=(PointsSettings("laparoscope", POSE),))
    app = App(parse_scene(SCENE), port=free_port(), session_dir=tmp_path / "s", edge=12.0, k=12,
              cache_root=cache_root, tracking=cfg)
    in_camera = np.array([[10.0, 20.0, 90.0], [11.0, 21.0, 101.5]])
    pose = _camera_to_reference()
    try:
        assert app.start().wait(600) and app.core.failed is None, app.core.failed
        wait_until(server.is_connected)
        t = time.time()
        server.send_message(pyigtl.TransformMessage(pose, timestamp=t, device_name=POSE), wait=True)
        server.send_message(pyigtl.PointMessage(positions=in_camera, device_name="laparoscope", timestamp=t + 0.01),
                            wait=True)
        wait_until(lambda: len(app.core.session.live_points) >= 2)
        assert [p[3] for p in app.core.session.live_points] == ["laparoscope", "laparoscope"]
        data = app.core.data()["laparoscope"]
        simulated = app.core.sd.sourced["laparoscope"]
        np.testing.assert_array_equal(data[:len(simulated)], simulated)
        np.testing.assert_allclose(data[len(simulated):], in_camera @ pose[:3, :3].T + pose[:3, 3], atol=1e-4)
        assert any(line.startswith(f"{POSE}: ") for line in app.live.link.status_lines())  # its pose is watched
    finally:
        app.live.stop()
        app.server.stop()
        app.view2d.stop()
        server.stop()


def test_points_are_placed_by_the_pose_at_their_own_time_not_the_latest():
    """A depth matcher sends its points after the images it matched: the camera has moved
    since. They are placed by the pose interpolated at their timestamp (slerp, here checked
    against the rotation composed by hand: Ra · (Raᵀ Rb)^f)."""
    from navapp.tracking.receivers import Message

    a = _camera_to_reference()
    b = a.copy()
    b[:3, :3] = Rotation.from_euler("zy", [25.0, -10.0], degrees=True).as_matrix() @ a[:3, :3]
    b[:3, 3] += [8.0, -6.0, 4.0]
    rx = PointsReceiver("laparoscope", ("laparoscope",), POSE, max_pose_age_s=0.2)
    t = 1000.0
    for stamp, m in ((t, a), (t + 0.1, b)):
        ev = rx.receive(Message("TRANSFORM", POSE, 0.0, stamp, pyigtl.TransformMessage(m, device_name=POSE)))
        rx.keep(ev)
    in_camera = np.array([[1.0, -2.0, 95.0], [30.0, 5.0, 140.0]])
    got = rx.receive(Message("POINT", "laparoscope", 0.0, t + 0.04,
                             pyigtl.PointMessage(positions=in_camera, device_name="laparoscope")))
    assert isinstance(got, SourcePoints)
    Ra = Rotation.from_matrix(a[:3, :3])
    R = (Ra * Rotation.from_rotvec(0.4 * (Ra.inv() * Rotation.from_matrix(b[:3, :3])).as_rotvec())).as_matrix()
    shift = 0.6 * a[:3, 3] + 0.4 * b[:3, 3]
    np.testing.assert_allclose(got.points, in_camera @ R.T + shift, atol=1e-9)
    latest = in_camera @ b[:3, :3].T + b[:3, 3]
    assert np.linalg.norm(got.points - latest, axis=1).min() > 5.0  # the latest pose would be centimetres off
    def place(stamp):
        return rx.receive(Message("POINT", "laparoscope", 0.0, stamp,
                                  pyigtl.PointMessage(positions=in_camera, device_name="laparoscope")))

    np.testing.assert_allclose(place(t + 0.1).points, latest, atol=1e-9)  # at a pose's own time: that pose
    with pytest.raises(ValueError, match="first kept CameraToReference is 0.50 s from the points"):
        place(t - 0.5)
    # a gap in the pose stream (the camera out of view: PLUS's invalid poses are dropped) is not bridged
    c = b.copy()
    c[:3, 3] += [40.0, 0.0, 0.0]
    rx.keep(rx.receive(Message("TRANSFORM", POSE, 0.0, t + 1.1, pyigtl.TransformMessage(c, device_name=POSE))))
    with pytest.raises(ValueError, match=r"poses -0.40 s and \+0.60 s from them"):
        place(t + 0.5)
    assert isinstance(place(t + 1.2), SourcePoints)  # the newest pose, 0.1 s before


def test_a_new_kind_of_tool_is_its_receiver_module_alone_config_and_client_unchanged(tmp_path, monkeypatch):
    """A tracked needle, written as a receiver module would be (its settings dataclass, their
    keys and parser, ``make``) and found as ``receivers.modules`` finds one: the tracking file
    reads its key, refuses its bad values and a clash with another tool's device in one line,
    and the client builds and watches its receiver — with no line of ``config`` or ``client``
    knowing it."""
    from dataclasses import dataclass
    from types import ModuleType

    from navapp.errors import InputError
    from navapp.tracking import receivers
    from navapp.tracking.client import HEADER, parse_header
    from navapp.tracking.events import StylusSample
    from navapp.tracking.receivers.base import device_name, pose_matrix, seen

    @dataclass(frozen=True)
    class NeedleSettings:
        device: str = "NeedleToReference"
        source: str = "needle"

        @property
        def named(self):
            return (("devices.needle", self.device),)

    @dataclass
    class NeedleReceiver:
        device: str
        source: str = "needle"
        devices = property(lambda self: (self.device,))
        latest = None

        def takes(self, mtype, device):
            return mtype == "TRANSFORM" and device == self.device

        def receive(self, message):
            m = pose_matrix(message)
            return StylusSample(message.t, message.t_sent, m[:3, 3].copy(), m)

        def keep(self, event):
            self.latest = event

        def fresh(self, status):
            return seen(status, self.device)

    def parse(source, data, path=None):
        device = data.get("devices", {}).get("needle", NeedleSettings.device)
        if device == "Needle":
            raise InputError("devices.needle: a TRANSFORM is named <Tool>To<Frame>", path)
        return NeedleSettings(device_name(device, "devices.needle", path), source)

    needle = ModuleType("navapp.tracking.receivers.needle")
    needle.KEYS, needle.TABLES, needle.parse = {"devices": {"needle": str}}, (), parse
    needle.default = lambda source: NeedleSettings(source=source)
    needle.make = lambda settings, shared: NeedleReceiver(settings.device, settings.source)
    found = receivers.modules

    monkeypatch.setattr(receivers, "modules", lambda: {**found(), "needle": needle})
    good = tmp_path / "tracking.toml"
    good.write_text('[devices]\nneedle = "BiopsyToReference"\nstylus = "PointerToReference"\n')
    cfg = load_config(good)
    assert [t.source for t in cfg.tools] == ["stylus", "ius", "laparoscope", "needle"]
    assert cfg.tool("needle", NeedleSettings) == NeedleSettings("BiopsyToReference")
    assert cfg.tool("stylus", StylusSettings).device == "PointerToReference"
    assert TrackingConfig().tool("needle", NeedleSettings) == NeedleSettings()
    for text, problem in [('[devices]\nneedle = 3\n', "devices.needle must be a str"),
                          ('[devices]\nneedle = "Needle"\n', "<Tool>To<Frame>"),
                          ('[devices]\nneedle = "ABiopsyNeedleToReference"\n', "1–20 bytes"),
                          ('[devices]\nneedle = "ProbeToReference"\n',
                           "devices.needle 'ProbeToReference' is another device's name"),
                          ('[devices]\nneedles = "X"\n', "(known: stylus, probe, image, image_pose, needle)")]:
        refused_in_one_line(load_config, tmp_path / "bad.toml", text, problem)

    client = TrackingClient(cfg)  # never started: a message is fed by hand
    assert list(client.status()) == ["PointerToReference", "ProbeToReference", "Image_Reference",
                                     "BiopsyToReference"]
    m = _camera_to_reference().astype(np.float32)
    raw = pyigtl.TransformMessage(m, timestamp=time.time(), device_name="BiopsyToReference").pack()
    fields = parse_header(raw[:HEADER.size])
    client._on_message(fields, raw[HEADER.size:])
    got = client.receiver("needle")
    assert isinstance(got, NeedleReceiver) and got.latest is not None
    np.testing.assert_allclose(got.latest.tip, m[:3, 3], atol=1e-4)
    assert client.status()["BiopsyToReference"].state == "seen" and client.fresh("needle")
