"""What the viewer's access control costs in time: the front before viser (page load, a scene
update's delivery, a large message) against viser reached directly, side by side in one
process, and one action-log line (written and fsync'd) as a click adds it.

    python notes/scripts/bench_access.py [--repeats 30]

Prints medians (and the 10th-90th percentiles) in milliseconds. Both websocket clients are
connected at once and receive the same broadcasts, so the two figures of a row share the
machine's load at each moment.
"""

import argparse
import asyncio
import socket
import statistics
import tempfile
import threading
import time
import urllib.request

import numpy as np
import viser
from websockets.asyncio.client import connect

from navapp.app.access import Access, Role
from navapp.app.actions import Act, ActionLog
from navapp.app.front import Front


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def spread(xs):
    q = np.percentile(xs, [10, 50, 90])
    return f"median {q[1]:7.2f} ms  (p10 {q[0]:.2f}, p90 {q[2]:.2f}, n = {len(xs)})"


def page_loads(direct, front, n):
    t = {"direct": [], "front": []}
    for _ in range(n):
        for name, url in (("direct", direct), ("front", front)):
            t0 = time.perf_counter()
            with urllib.request.urlopen(urllib.request.Request(url, headers={"Accept-Encoding": "gzip"})) as r:
                r.read()
            t[name].append(1000 * (time.perf_counter() - t0))
    return t


def deliveries(server, ports, token, n, points):
    """ms from a broadcast's flush to its arrival at a direct and a fronted client."""
    sub = [f"viser-v{viser.__version__}"]
    arrivals: dict[str, list[float]] = {"direct": [], "front": []}
    sent: list[float] = []
    ready = threading.Event()
    done = threading.Event()

    async def client(name, port, query):
        async with connect(f"ws://127.0.0.1:{port}/{query}", subprotocols=sub, max_size=None,
                           compression=None) as ws:
            ready.set()
            while not done.is_set():
                try:
                    await asyncio.wait_for(ws.recv(), 0.5)
                except TimeoutError:
                    continue
                if len(arrivals[name]) < len(sent):
                    arrivals[name].append(time.perf_counter())

    def run():
        async def both():
            await asyncio.gather(client("direct", ports[0], ""), client("front", ports[1], f"?token={token}"))
        asyncio.run(both())

    th = threading.Thread(target=run, daemon=True)
    th.start()
    ready.wait(10)
    time.sleep(1.5)  # the backlog replayed to both
    rng = np.random.default_rng(0)
    for i in range(n):
        pts = rng.random((points, 3)).astype(np.float32)
        t0 = time.perf_counter()
        sent.append(t0)
        server.scene.add_point_cloud(f"/bench{i % 4}", pts, colors=(255, 0, 0), point_size=1.0)
        server.flush()
        end = time.monotonic() + 10
        while (len(arrivals["direct"]) <= i or len(arrivals["front"]) <= i) and time.monotonic() < end:
            time.sleep(0.0005)
        time.sleep(0.05)
    done.set()
    th.join(5)
    return {k: [1000 * (a - s) for a, s in zip(v, sent, strict=False)] for k, v in arrivals.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    a = ap.parse_args()
    token = "bench-token-" + "x" * 30
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    front = Front(Access(token, "observer-" + "y" * 30), server.get_port(), "127.0.0.1", free_port())
    try:
        t = page_loads(f"http://127.0.0.1:{server.get_port()}/", f"http://127.0.0.1:{front.port}/?token={token}",
                       a.repeats)
        print(f"page (index.html, gzip)   direct {spread(t['direct'])}")
        print(f"                          front  {spread(t['front'])}")
        for points in (100, 200_000):
            d = deliveries(server, (server.get_port(), front.port), token, a.repeats, points)
            print(f"scene update, {points:>7} points ({points * 12 / 1e6:.1f} MB)  direct {spread(d['direct'])}")
            print(f"                                       front  {spread(d['front'])}")
    finally:
        front.stop()
        server.stop()
    with tempfile.TemporaryDirectory(dir=".") as d:
        log = ActionLog(d)
        ts = []
        for i in range(max(a.repeats, 100)):
            t0 = time.perf_counter()
            log.append("tab 0", Role.EDITOR, Act.VERTEX, f"vertex {i}")
            ts.append(1000 * (time.perf_counter() - t0))
        print(f"action log line (fsync'd, in ./)  {spread(ts)}")
    extra = statistics.median(t["front"]) - statistics.median(t["direct"])
    print(f"(the front adds {extra:+.2f} ms to a page load, medians)")


if __name__ == "__main__":
    main()
