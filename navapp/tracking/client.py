"""OpenIGTLink client: TRANSFORM and IMAGE messages from a PLUS server (or 3D Slicer), and
POINT messages of a data source (``features.SOURCED``, device named as its
feature), turned into typed events (``events.py``) by each source's receiver (``receivers``),
with per-device watchdog status, reconnection, and a stylus digitiser fed on the way.

Built on pyigtl's ``OpenIGTLinkClient`` (its thread, start/stop and outgoing queue, and
its message classes for decoding), with the receive loop replaced, because pyigtl 0.3's
loop (a) keeps only the latest message per device, so a consumer polling slower than the
stream loses samples; (b) never notices a server that closed the connection (recv returns
b"" forever, no reconnect); (c) does not check the CRC; (d) on a corrupt header waits up to
5 s for a body of any announced size. Here every message is decoded as it arrives; a
message with a bad CRC, an undecodable body, an unknown type or device, or a timestamp
older than its device's last one is logged and skipped (the connection stays up); bytes
that are not an OpenIGTLink header at all drop the connection, which is reopened (the
stream cannot be resynchronised: PLUS and Slicer do the same).

Frames: coordinates are passed through in the tracker's Reference frame, mm. navapp's
preoperative model is LAS (mm); the registration's rigid part maps model → tracker space,
so it absorbs whatever frame the tracker reports (a PLUS Reference, a Slicer RAS scene):
no conversion is made or needed here. 3D Slicer shows these coordinates as RAS.
"""

import logging
import queue
import socket
import struct
import threading
import time
from collections import Counter, deque

import pyigtl
from pyigtl.messages import CRC64, MessageBase

from .config import TrackingConfig
from .digitiser import Digitiser
from .events import ConnectionStatus, ProbePose, ProbeSample, Skipped, StylusSample, TransformSample
from .receivers import Message, Receiver, Shared, build
from .receivers.base import pose_matrix
from .receivers.ius import ProbeReceiver
from .receivers.stylus import StylusReceiver
from .watchdog import Watchdog

log = logging.getLogger("navapp.tracking")

HEADER = struct.Struct("> H 12s 20s I I Q Q")  # version, type, device, seconds, fraction, body size, CRC
HEADER_SIZE = HEADER.size  # 58
MAX_BODY = 256 << 20  # larger is garbage: a 4k RGB frame is 25 MB
POLL_S = 0.02  # recv timeout: the loop's tick (watchdog checks, outgoing messages)
CONNECT_TIMEOUT_S = 2.0
STALL_S = 5.0  # a message begun but not finished for this long: the server hangs, reconnect
_TYPE_CHARS = set(b"ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_")


class ProtocolError(Exception):
    """The byte stream is not OpenIGTLink: drop the connection."""


def parse_header(raw) -> dict | None:
    """Header fields, or None when the 58 bytes cannot be an OpenIGTLink header."""
    version, mtype, device, sec, frac, size, crc = HEADER.unpack_from(raw)
    mtype = bytes(mtype).rstrip(b"\0")
    if version not in (1, 2, 3) or not mtype or not set(mtype) <= _TYPE_CHARS or size > MAX_BODY:
        return None
    try:
        name = bytes(device).split(b"\0", 1)[0].decode("utf-8")
    except UnicodeDecodeError:
        return None
    nanos = pyigtl.messages._igtl_frac_to_nanosec(frac)
    return {"header_version": version, "message_type": mtype.decode(), "device_name": name,
            "timestamp": sec + nanos * 1e-9, "body_size": size, "crc": crc}


class _Link(pyigtl.OpenIGTLinkClient):
    """pyigtl's client with the receive loop of this module (see the module doc)."""

    def __init__(self, host, port, reconnect_s, on_message, on_connection, on_tick):
        super().__init__(host=host, port=port, start_now=False)
        self.reconnect_s = reconnect_s
        self.on_message, self.on_connection, self.on_tick = on_message, on_connection, on_tick
        self._wake = threading.Event()
        self._partial_since = time.monotonic()
        self._started: bool = False  # pyigtl's flag, set by its start()

    def stop(self, timeout=5.0):
        if not self._started:
            return
        self._started = False
        self.communication_thread_stop_requested = True
        self._wake.set()
        self._client_thread.join(timeout)

    def _client_thread_function(self):
        sock, buf = None, bytearray()
        while not self.communication_thread_stop_requested:
            if sock is None:
                try:
                    sock = socket.create_connection((self.host, self.port), timeout=CONNECT_TIMEOUT_S)
                    sock.settimeout(POLL_S)
                    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                except OSError:
                    sock = None
                    self.on_tick()
                    self._wake.wait(self.reconnect_s)
                    continue
                buf = bytearray()
                self._connected = True
                with self.lock_outgoing_messages:
                    self.outgoing_messages.clear()  # nothing stale from a previous connection
                self.on_connection(True, "")
            try:
                self._pump(sock, buf)
                while self._send_queued_message_from_socket(sock):
                    pass
            except (OSError, ProtocolError) as exc:
                reason = str(exc) or type(exc).__name__
                try:
                    sock.close()
                except OSError:
                    pass
                sock = None
                self._connected = False
                self.on_connection(False, reason)
            self.on_tick()
        if sock is not None:
            sock.close()
        self._connected = False
        self.communication_thread_stopped = True

    def _pump(self, sock, buf):
        try:
            chunk = sock.recv(1 << 20)
        except TimeoutError:
            if buf and time.monotonic() - self._partial_since > STALL_S:
                raise ConnectionError(f"a message stalled for {STALL_S:g} s") from None
            return
        if not chunk:
            raise ConnectionError("connection closed by the server")
        if not buf:
            self._partial_since = time.monotonic()
        buf += chunk
        while len(buf) >= HEADER_SIZE:
            fields = parse_header(buf)
            if fields is None:
                raise ProtocolError(f"not an OpenIGTLink stream (bytes {bytes(buf[:16])!r}…)")
            end = HEADER_SIZE + fields["body_size"]
            if len(buf) < end:
                try:  # the rest of a large body (an image) is on its way
                    more = sock.recv(max(end - len(buf), 1 << 16))
                except TimeoutError:
                    return
                if not more:
                    raise ConnectionError("connection closed by the server mid-message")
                buf += more
                continue
            body = bytes(buf[HEADER_SIZE:end])
            del buf[:end]
            self._partial_since = time.monotonic()
            self.on_message(fields, body)


class TrackingClient:
    """Connects to ``config.host:config.port`` (PLUS or Slicer as server) in its own thread.

    Events (``events.py``) go to ``on_event`` (called in the client thread: keep it short)
    and/or to the ``events`` queue (bounded; the oldest is dropped when full). Each source's
    receiver (``receivers``: ``receiver(source)``) makes them and keeps its latest
    (``latest_stylus``, ``latest_probe_pose``, ``latest_frame`` read them); the stylus's
    feeds ``digitiser`` every sample in the client thread, so recording does not depend on
    anybody draining the queue. A TRANSFORM no receiver takes is passed on as a
    ``TransformSample``; any other message no receiver takes is ignored (counted).
    """

    def __init__(self, config: TrackingConfig | None = None, on_event=None, queue_size: int = 2000,
                 digitiser: Digitiser | None = None):
        self.config = config or TrackingConfig()
        c = self.config
        self.on_event = on_event
        self.events: queue.Queue = queue.Queue(maxsize=queue_size)
        self.digitiser = digitiser or Digitiser(c.rate_hz)
        self.receivers: tuple[Receiver, ...] = build(c.tools, Shared(self.digitiser, c.stale_s))
        self.watchdog = Watchdog([d for r in self.receivers for d in r.devices], c.stale_s, c.missing_s)
        self.counts: Counter[str] = Counter()  # "TRANSFORM", "IMAGE", … received; "skipped:<kind>"
        self.connects = 0
        self.connection = ConnectionStatus(False, f"{c.host}:{c.port}", 0)
        self._last_ts: dict = {}
        self._arrivals: dict = {}
        self._unknown_logged: set = set()
        self._link = _Link(c.host, c.port, c.reconnect_s, self._on_message, self._on_connection, self._on_tick)

    # ------------------------------------------------------------------ control
    def start(self) -> "TrackingClient":
        self._link.start()
        return self

    def stop(self):
        self._link.stop()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    @property
    def connected(self) -> bool:
        return self._link.is_connected()

    def status(self) -> dict:
        """device → ToolStatus (seen / stale / missing) now."""
        return self.watchdog.status()

    def receiver(self, source: str) -> Receiver:
        """The receiver of ``source`` (a ``features.TABLE`` source: "stylus", "ius", …)."""
        for r in self.receivers:
            if r.source == source:
                return r
        raise KeyError(f"no receiver for source {source!r}")

    def fresh(self, source: str, status: dict | None = None) -> bool:
        """What ``source``'s receiver keeps may be shown and used (its streams are seen) by
        ``status`` (the watchdog's, ``status()``; default now)."""
        return self.receiver(source).fresh(self.status() if status is None else status)

    @property
    def latest_stylus(self) -> StylusSample | None:
        r = self.receiver("stylus")
        assert isinstance(r, StylusReceiver)
        return r.latest

    @property
    def latest_probe_pose(self) -> ProbePose | None:
        r = self.receiver("ius")
        assert isinstance(r, ProbeReceiver)
        return r.latest_pose

    @property
    def latest_frame(self) -> ProbeSample | None:
        r = self.receiver("ius")
        assert isinstance(r, ProbeReceiver)
        return r.latest_frame

    def rate_hz(self, device: str) -> float:
        """Messages per second of ``device`` over its last (up to) 50 arrivals."""
        arr = self._arrivals.get(device)
        if not arr or len(arr) < 2 or arr[-1] <= arr[0]:
            return 0.0
        return (len(arr) - 1) / (arr[-1] - arr[0])

    def send(self, message: MessageBase) -> bool:
        """Queue a pyigtl message to the server on this connection (e.g. results to a
        Slicer that is the server); dropped while disconnected."""
        if not self.connected:
            return False
        return self._link.send_message(message, wait=False)

    def drain(self, timeout: float = 0.0) -> list:
        """All queued events (waiting up to ``timeout`` s for the first)."""
        out = []
        try:
            out.append(self.events.get(timeout=timeout) if timeout > 0 else self.events.get_nowait())
            while True:
                out.append(self.events.get_nowait())
        except queue.Empty:
            pass
        return out

    # ------------------------------------------------------------------ internals
    def _emit(self, ev):
        if self.on_event is not None:
            try:
                self.on_event(ev)
            except Exception:  # the app's bug must not stop tracking
                log.exception("tracking event callback failed")
        while True:
            try:
                self.events.put_nowait(ev)
                return
            except queue.Full:
                try:
                    self.events.get_nowait()
                except queue.Empty:
                    pass

    def _skip(self, kind, device, detail):
        self.counts[f"skipped:{kind}"] += 1
        key = (kind, device)
        level = logging.WARNING if key not in self._unknown_logged else logging.DEBUG
        self._unknown_logged.add(key)
        log.log(level, "skipped %s message from %r: %s", kind, device, detail)
        self._emit(Skipped(time.monotonic(), kind, device, detail))

    def _on_connection(self, up: bool, reason: str):
        if up:
            self.connects += 1
            self._last_ts.clear()  # a restarted server may have another clock
            log.info("connected to %s:%s", self.config.host, self.config.port)
        else:
            log.warning("connection to %s:%s lost: %s", self.config.host, self.config.port, reason)
            if reason.startswith("not an OpenIGTLink"):
                self._skip("garbage", "", reason)
        self.connection = ConnectionStatus(up, f"{self.config.host}:{self.config.port}", self.connects, reason)
        self._emit(self.connection)

    def _on_tick(self):
        for s in self.watchdog.changes():
            self._emit(s)

    def _on_message(self, fields, body):
        now = time.monotonic()
        mtype, device = fields["message_type"], fields["device_name"]
        if CRC64(body) != fields["crc"]:
            return self._skip("malformed", device, f"{mtype}: CRC mismatch")
        msg = MessageBase.create_message(mtype)
        if msg is None:
            return self._skip("unknown", device, f"message type {mtype}")
        try:
            msg.unpack(fields, body)
        except Exception as exc:  # pyigtl raises whatever struct/numpy raise
            return self._skip("malformed", device, f"{mtype}: {type(exc).__name__}: {exc}")
        receiver = next((r for r in self.receivers if r.takes(mtype, device)), None)
        if receiver is None and mtype != "TRANSFORM":
            self.counts[f"ignored:{mtype}"] += 1  # STRING, another device's POINT, another image stream, …
            log.debug("ignored %s message from %r", mtype, device)
            return None
        if msg.metadata.get("TransformStatus", "OK").upper() == "INVALID":  # PLUS: tool out of view
            self.counts["invalid"] += 1
            return None
        ts = fields["timestamp"]
        last = self._last_ts.get(device)
        if last is not None and ts < last:
            return self._skip("out_of_order", device, f"timestamp {ts:.6f} before {last:.6f}")
        message = Message(mtype, device, now, ts, msg)
        try:
            ev = receiver.receive(message) if receiver is not None else \
                TransformSample(now, ts, device, pose_matrix(message))
        except ValueError as exc:
            return self._skip("malformed", device, f"{mtype}: {exc}")
        if ev is None:
            return None
        self._last_ts[device] = ts
        self.counts[mtype] += 1
        self.watchdog.seen(device, now)
        self._arrivals.setdefault(device, deque(maxlen=50)).append(now)
        if receiver is not None:
            receiver.keep(ev)
        self._emit(ev)
        return None
