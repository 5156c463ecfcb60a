"""``navapp replay SCENE``: an OpenIGTLink server that plays a simulated scene as a
PlusServer would — the demo without hardware, and the tracking tests' fixture.

Every tick (``rate_hz``, default 25) it sends, as PLUS does with its default names:
- TRANSFORM ``StylusTipToReference``: the stylus tip sweeping the scene's swath pattern at
  40 mm/s (the viewer's pace at 1×), along the scene's digitised points in sweep order
  (``SceneData.stylus_path``), over and over;
- TRANSFORM ``ProbeToReference``: the probe resting ``dwell_s`` at each of the scene's iUS
  plane poses and gliding (``move_s``; translation linear, rotation slerp) to the next;
- IMAGE ``Image_Reference``: a B-mode frame whose matrix is ImageToReference (PLUS's
  ``EmbeddedTransformToFrame="Reference"``): the plane's image at rest, and in transit
  frames simulated at ``transit_frames`` poses along the way (made once, at start);
- POINT ``<feature>`` for every point source the scene simulated (``features.SOURCED``: the
  laparoscope's depth points), as its depth matcher sends them: the points as recorded, in
  Reference, once to each client that connects (a scene's source sees one view; sending it
  every tick would add the same points to the viewer's session again and again). When the
  tracking config (``names``) makes the source a tracked tool (``[tools.<source>] pose``), its
  points go in the tool's own frame and its TRANSFORM, the pose the tracker reported when they
  were acquired (the source's ``tool_to_tracker`` in ``truth/report.json``), every tick.

A scene without iUS planes plays no probe and no frames, if it has a point source to play.

Only the scene's declared effects apply: the stylus points already carry the scene's
tracking noise (the simulator added it when it digitised them); with ``tracking_noise``
declared the probe's streamed position gets the same noise per message (the image's
embedded pose with it, as PLUS derives one from the other); transit frames are simulated
with the scene's effects (``acquire_free_plane``). A scene's declared ``latency`` effect
(or ``--latency-ms``) sends every message that much after the moment it describes (its
timestamp is that moment).

Frames: the scene's tracker space is the Reference frame (mm).

pyigtl's server serves one client at a time (PlusServer serves several): a second client
waits until the first disconnects.
"""

import json
import logging
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import pyigtl

from ..errors import InputError, NavappError
from ..features import BY_NAME
from ..geometry.transforms import apply, homogeneous, interpolate_pose, inverse
from .config import TrackingConfig
from .receivers.ius import ProbeSettings, full_image_matrix
from .receivers.points import PointsSettings
from .receivers.stylus import StylusSettings

log = logging.getLogger("navapp.tracking")

STYLUS_MM_PER_S = 40.0  # the viewer's sweep at 1× (navapp/app/stylus.py)


@dataclass
class ProbeKeyframe:
    t: float  # seconds into the probe's cycle at which this frame becomes current
    pose: np.ndarray  # (4, 4) ProbeToReference at which the image was acquired
    image: np.ndarray  # (H, W) uint8


@dataclass
class ReplayScript:
    """What to play: a stylus polyline and a probe cycle. Independent of the simulator,
    so tests can play a small synthetic script."""
    stylus_path: np.ndarray  # (N, 3) mm
    probe_stops: list  # [(4, 4)] poses the probe rests at
    keyframes: list  # [ProbeKeyframe] sorted by t, within one cycle
    cycle_s: float  # length of the probe's cycle
    image_to_probe: np.ndarray = field(default_factory=lambda: ProbeSettings().image_to_probe)
    dwell_s: float = 2.0
    move_s: float = 1.0
    stylus_mm_per_s: float = STYLUS_MM_PER_S
    probe_noise_mm: float = 0.0  # tracking_noise sd, when the scene declares it
    seed: int = 0
    points: dict = field(default_factory=dict)  # feature → (N, 3) mm in Reference: a point source's, sent once
    poses: dict = field(default_factory=dict)  # source → (4, 4) ToolToReference its points were acquired at

    def __post_init__(self):
        p = np.asarray(self.stylus_path, float)
        self.stylus_path = p
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1) if len(p) > 1 else np.zeros(0)
        self._cum = np.concatenate([[0.0], np.cumsum(seg)])
        self._kf_t = np.array([k.t for k in self.keyframes])

    @property
    def stylus_length_mm(self) -> float:
        return float(self._cum[-1])

    def stylus_at(self, t: float) -> np.ndarray:
        """Tip position (3,) at ``t`` s into the sweep (repeats when the sweep ends)."""
        p = self.stylus_path
        if len(p) == 1 or self._cum[-1] == 0:
            return p[0].copy()
        s = (self.stylus_mm_per_s * t) % self._cum[-1]
        i = int(np.clip(np.searchsorted(self._cum, s, side="right") - 1, 0, len(p) - 2))
        f = (s - self._cum[i]) / max(self._cum[i + 1] - self._cum[i], 1e-12)
        return p[i] + f * (p[i + 1] - p[i])

    def probe_at(self, t: float) -> np.ndarray:
        """ProbeToReference (4, 4) at ``t`` s: rest at each stop, glide to the next."""
        stops = self.probe_stops
        if len(stops) == 1:
            return np.array(stops[0], float)
        period = self.dwell_s + self.move_s
        tc = t % (period * len(stops))
        i = int(tc // period)
        u = tc - i * period
        a, b = np.asarray(stops[i], float), np.asarray(stops[(i + 1) % len(stops)], float)
        if u <= self.dwell_s:
            return a.copy()
        return interpolate_pose(a, b, (u - self.dwell_s) / self.move_s)

    def frame_at(self, t: float) -> ProbeKeyframe:
        tc = t % self.cycle_s
        i = int(np.clip(np.searchsorted(self._kf_t, tc, side="right") - 1, 0, len(self.keyframes) - 1))
        return self.keyframes[i]


def script_from_scene(scene, transit_frames: int = 6, dwell_s: float = 2.0, move_s: float = 1.0,
                      cache_root=None, edge: float | None = None) -> ReplayScript:
    """The scene simulated (or loaded from the cache) as the viewer does, made playable.
    ``edge``: the viewer's registration mesh size, to share its cached simulation (what is
    played does not depend on it)."""
    from ..simulation.scenedata import acquire_free_plane, load_scene_data
    from ..simulation.sources import registered

    sd = load_scene_data(scene, cache_root) if edge is None else load_scene_data(scene, cache_root, edge)
    if not sd.planes and not sd.sourced:
        raise InputError("the scene has no iUS planes ([ius] planes = 0) and no point source to replay", scene.source)
    if len(sd.stylus_path) == 0:
        raise InputError("the scene has no stylus points to replay", scene.source)
    stops = [p.probe_to_tracker for p in sd.planes]
    period = dwell_s + move_s
    keyframes = []
    for i, plane in enumerate(sd.planes):
        keyframes.append(ProbeKeyframe(i * period, plane.probe_to_tracker, plane.image))
        nxt = stops[(i + 1) % len(stops)]
        for j in range(1, transit_frames + 1):
            f = j / (transit_frames + 1)
            pose = interpolate_pose(plane.probe_to_tracker, nxt, f)
            frame = acquire_free_plane(sd, 1000 + i * 100 + j, pose)
            assert frame.image is not None  # acquired with its image
            keyframes.append(ProbeKeyframe(i * period + dwell_s + (f - 0.5 / (transit_frames + 1)) * move_s,
                                           pose, frame.image))
    eff = {e.kind: e.params for e in scene.effects}
    report = json.loads((sd.case_dir / "truth" / "report.json").read_text())
    poses = {}
    for source in {BY_NAME[k].source for k in sd.sourced}:
        pose = report.get(registered()[source].report_as, {}).get("tool_to_tracker")
        if pose is not None:
            poses[source] = np.array(pose, float)
    return ReplayScript(sd.stylus_path, stops, keyframes, period * len(stops),
                        full_image_matrix(sd.probe.image_to_probe()), dwell_s, move_s,
                        probe_noise_mm=eff.get("tracking_noise", {}).get("sd_mm", 0.0), seed=scene.seed,
                        points={k: np.asarray(v, float) for k, v in sd.sourced.items() if len(v)}, poses=poses)


class _Handler(pyigtl.comm.TCPRequestHandler):
    """pyigtl's connection handler without the traceback it prints when a client leaves."""

    def handle(self):
        server = self.server
        server.connections = getattr(server, "connections", 0) + 1  # which client this is (a replay sends once to each)
        server._connected = True
        self.request.settimeout(0.01)
        log.info("OpenIGTLink client connected from %s:%s", *self.client_address[:2])
        while not server.communication_thread_stop_requested:
            try:
                while server._receive_message_from_socket(self.request):
                    if server.communication_thread_stop_requested:
                        break
                while server._send_queued_message_from_socket(self.request):
                    pass
            except (OSError, ValueError, KeyError) as exc:
                log.info("OpenIGTLink client left (%s)", exc)
                break
        server._connected = False


def quiet_server(port: int) -> pyigtl.OpenIGTLinkServer:
    """A pyigtl server on 127.0.0.1:``port`` (0: a free one), not yet started, that leaves
    navapp's Ctrl-C handling alone (pyigtl installs SIGINT/SIGTERM handlers: put back at
    once) and does not print tracebacks when a client disconnects."""
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    server = pyigtl.OpenIGTLinkServer(port=port, local_server=True, start_now=False)
    for s, h in previous.items():
        signal.signal(s, h)
    server.RequestHandlerClass = _Handler
    return server


class ReplayServer:
    """Plays a ``ReplayScript`` on 127.0.0.1:``port`` (0: a free port, see ``.port``).

    ``sent`` keeps (timestamp, device, float32 4×4) of every TRANSFORM sent — exactly the
    values on the wire — so a test can compare what a client recorded with what was sent.
    """

    def __init__(self, script: ReplayScript, port: int = 18944, rate_hz: float = 25.0,
                 names: TrackingConfig | None = None, latency_s: float = 0.0, keep_sent: int = 200_000):
        self.script, self.rate_hz, self.latency_s = script, float(rate_hz), float(latency_s)
        self.names = names or TrackingConfig()
        self.sent: deque = deque(maxlen=keep_sent)
        self.ticks = 0
        self.frames_sent = 0
        self.points_sent = 0  # POINT messages sent (one per point feature per connection)
        self._points_to = 0  # the last client (``_Handler``'s count) the point sources' points went to
        # source → (its TRANSFORM's name, ToolToReference) for each point source the config tracks
        self.tools: dict[str, tuple[str, np.ndarray]] = {}
        for source in dict.fromkeys(BY_NAME[k].source for k in script.points):
            device = self.names.tool(source, PointsSettings).pose
            if device is None:
                continue
            if source not in script.poses:
                raise InputError(f"the tracking config places the {source}'s points by {device}, but the scene "
                                 f"records no pose of the {source}: replay it without [tools.{source}]")
            # as the wire carries it: the client places the points by the float32 pose
            self.tools[source] = (device, np.asarray(script.poses[source], np.float32).astype(float))
        self._rng = np.random.default_rng(script.seed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        try:
            self._server = quiet_server(port)
        except OSError as exc:

            raise NavappError(f"cannot listen on 127.0.0.1:{port}: {exc.strerror or exc}") from None
        self.port = self._server.server_address[1]
        self.t0: float | None = None

    def start(self) -> "ReplayServer":
        self._server.start()
        self.t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="navapp-replay", daemon=True)
        self._thread.start()
        return self

    def stop(self):
        """Stop sending, close the client connection and the listening socket."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self._server.stop()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    @property
    def connected(self) -> bool:
        return self._server.is_connected()

    def _run(self):
        period = 1.0 / self.rate_hz
        wall0 = time.time()
        t0 = self.t0
        assert t0 is not None  # set by start() before the thread runs
        next_t = t0
        while not self._stop.is_set():
            now = time.monotonic()
            if now < next_t:
                self._stop.wait(next_t - now)
                continue
            next_t += period
            if next_t < now - 1.0:  # fell far behind (a stalled machine): do not burst
                next_t = now + period
            t = now - t0 - self.latency_s  # the moment these messages describe
            if self._server.is_connected():
                try:
                    self._send_tick(t, wall0 + t)
                    client = getattr(self._server, "connections", 0)
                    if client != self._points_to:
                        self._points_to = client
                        self._send_points(wall0 + t)
                except Exception:  # noqa: BLE001 — a replay must keep playing
                    log.exception("replay tick failed")
            self.ticks += 1

    def _send_points(self, stamp):
        """Each point source's recorded points, one POINT message per feature (its name): in
        Reference, or in the tool's own frame for a tracked one."""
        for feature, pts in self.script.points.items():
            tool = self.tools.get(BY_NAME[feature].source)
            if tool is not None:
                pts = apply(inverse(tool[1]), pts)
            msg = pyigtl.PointMessage(positions=np.asarray(pts, np.float32), timestamp=stamp, device_name=feature)
            self._server.send_message(msg, wait=False)
            self.points_sent += 1

    def _send_tick(self, t, stamp):
        s = self.script
        stylus, ius = self.names.tool("stylus", StylusSettings), self.names.tool("ius", ProbeSettings)
        tip = homogeneous(np.eye(3), s.stylus_at(t))
        m32 = np.asarray(tip, np.float32)
        self._server.send_message(pyigtl.TransformMessage(m32, timestamp=stamp, device_name=stylus.device), wait=False)
        self.sent.append((stamp, stylus.device, m32))
        for device, pose in self.tools.values():  # a tracked point source's tool, held where it acquired
            m32 = np.asarray(pose, np.float32)
            self._server.send_message(pyigtl.TransformMessage(m32, timestamp=stamp, device_name=device), wait=False)
            self.sent.append((stamp, device, m32))
        if not s.probe_stops:  # a scene without iUS planes: its stylus and its point sources only
            return
        probe = s.probe_at(t)
        frame = s.frame_at(t)
        image_pose = frame.pose
        if s.probe_noise_mm:
            shift = self._rng.normal(scale=s.probe_noise_mm, size=3)
            probe = probe.copy()
            probe[:3, 3] += shift
            image_pose = image_pose.copy()
            image_pose[:3, 3] += shift
        m32 = np.asarray(probe, np.float32)
        self._server.send_message(pyigtl.TransformMessage(m32, timestamp=stamp, device_name=ius.probe), wait=False)
        self.sent.append((stamp, ius.probe, m32))
        img = pyigtl.ImageMessage(np.ascontiguousarray(frame.image)[None], image_pose @ s.image_to_probe,
                                  world_coordinate_system="ras", timestamp=stamp, device_name=ius.image)
        self._server.send_message(img, wait=False)
        self.frames_sent += 1


def run_replay(scene, port=18944, rate_hz=25.0, latency_s=0.0, transit_frames=6, duration_s=None, out=print,
               names: TrackingConfig | None = None):
    """The ``navapp replay`` command: play until Ctrl-C (or ``duration_s``). ``names``: the
    tracking config whose device names it sends under and whose ``[tools.<source>]`` make a
    point source a tracked tool (default PLUS's names, points in Reference)."""
    from .. import progress

    names = names or TrackingConfig()
    with progress.stage(f"preparing scene {scene.name} for replay"):
        script = script_from_scene(scene, transit_frames)
    server = ReplayServer(script, port, rate_hz, names=names, latency_s=latency_s).start()
    stylus, ius = names.tool("stylus", StylusSettings), names.tool("ius", ProbeSettings)
    points = "".join(f", {k} ({len(v)} points, POINT, once to each client)" for k, v in script.points.items())
    tools = "".join(f", {device} (TRANSFORM)" for device, _ in server.tools.values())
    probe = f", {ius.probe} (TRANSFORM), {ius.image} (IMAGE)" if script.probe_stops else ""
    out(f"navapp: replaying {scene.name} on 127.0.0.1:{server.port} as PLUS would: "
        f"{stylus.device}{probe}{' (TRANSFORM)' if not probe else ''}{tools} at {rate_hz:g} Hz{points}; "
        f"stylus sweep {script.stylus_length_mm:.0f} mm at {script.stylus_mm_per_s:g} mm/s, "
        f"{len(script.probe_stops)} probe poses; Ctrl-C stops")
    t0 = time.monotonic()
    try:
        while duration_s is None or time.monotonic() - t0 < duration_s:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    secs = time.monotonic() - t0
    out(f"navapp: replay stopped after {secs:.1f} s, {server.frames_sent} frames sent")
    return {"seconds": round(secs, 1), "frames_sent": server.frames_sent, "port": server.port}
