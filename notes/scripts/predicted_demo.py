"""Issue 50, item 2 on the demo: the predicted error against the true one, over the organ, at the
surface and at each tumour, for the scenarios a surgeon meets — the stylus sweep alone, the sweep
and every plane, the same with a stray posterior vertex, and a gross pose (a few seconds of
digitising). Headless: the viewer's App on the built-in demo scene at ``navapp serve``'s
defaults (``--edge``, ``--k``), driven through its rooms.

    python notes/scripts/predicted_demo.py [--session DIR]

Prints one markdown row per scenario: predicted ÷ true (organ, surface, each tumour) where the
viewer shows a figure ("—" where it shows none: a pose not to be believed), and whether each
shown figure lies in [0.5, 3]."""

import argparse
import socket
import tempfile
import time
from pathlib import Path

import numpy as np

from navapp.app.server import App
from navapp.app.state import RunKind
from navapp.defaults import EDGE_MM, K
from navapp.simulation.probe import tracker_to_pixels
from navapp.simulation.scene import demo_scene

STRAY_MM = 35.0


def run(app, kind):
    assert app.runs.start(kind) is None
    app.core.worker.join(3600)
    return app.core.session.log[-1]


def ratios(app, entry) -> dict:
    res, reg = app.core.result, app.core.last_reg
    out = {}
    if reg.organ is not None and res.pose_warning is None:  # shown beside a believable pose only
        out["organ"] = reg.organ.mean_mm / entry.error_mean_mm
    if res.predicted_mm is not None:
        surf = app.core.model.basis.surface
        out["surface"] = float(res.predicted_mm.mean() / res.node_error_mm[surf].mean())
    for b in res.target_bands:
        out[b.name] = b.predicted_mm / entry.targets_mm[b.name] if np.isfinite(b.predicted_mm) else float("nan")
    return out


def only(app, live_points=(), planes=(), sweep=False):
    s = app.core.session
    s.stylus_count, s.contours = 0, []
    s.live_points = [[*map(float, p), "anterior"] for p in live_points]
    s.planes_added = list(planes)
    app.core.changed()
    if sweep:
        app.stylus.collect_now()


def wall(app):
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
    raise SystemExit("no demo plane shows enough posterior wall")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, default=None)
    args = ap.parse_args()
    folder = args.session or Path(tempfile.mkdtemp(prefix="predicted-demo-"))
    t0 = time.monotonic()
    with socket.socket() as s:  # a free port for the (unused) viewer
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    app = App(demo_scene(), port=port, session_dir=folder, edge=EDGE_MM, k=K)
    assert app.start().wait(7200) and app.core.failed is None, app.core.failed
    print(f"ready in {time.monotonic() - t0:.0f} s", flush=True)
    rows = []
    try:
        planes = sorted(i for i in app.core.planes if i < 1000)
        only(app, sweep=True)
        rows.append(("stylus sweep, surface only", run(app, RunKind.SURFACE)))
        rows[-1] = (*rows[-1], ratios(app, rows[-1][1]))
        only(app, planes=planes, sweep=True)
        e = run(app, RunKind.ALL)
        rows.append(("sweep + 16 planes, all data", e, ratios(app, e)))
        plane, verts = wall(app)
        cs = app.core.new_client_state()
        app.imaging.show(cs, plane)
        for c, r in verts:
            assert app.drawing.click(cs, c, r, "Posterior surface") is None
        assert app.drawing.command(cs, "Finish line") is None
        contour = app.core.session.contours[-1]
        (c0, r0), (c1, r1) = verts[0], verts[1]
        contour.vertices.insert(1, ((c0 + c1) // 2, (r0 + r1) // 2 + int(STRAY_MM / app.core.sd.probe.spacing_mm)))
        app.core.changed()
        e = run(app, RunKind.ALL)
        rows.append((f"the same + a posterior contour with a vertex {STRAY_MM:g} mm off", e, ratios(app, e)))
        sd = app.core.sd
        ant = sd.stylus_path[sd.stylus_labels == "anterior"]
        only(app, live_points=ant[np.argsort(np.linalg.norm(ant - ant[0], axis=1))[:40]])
        e = run(app, RunKind.SURFACE)
        rows.append(("gross pose: 40 stylus points", e, ratios(app, e)))
    finally:
        app.server.stop()
        app.view2d.stop()
    names = sorted({k for _, _, r in rows for k in r if k not in ("organ", "surface")})
    print("| scenario | true mean (mm) | organ | surface | " + " | ".join(names) + " | all in [0.5, 3] |")
    print("|---" * (5 + len(names)) + "|")
    for what, e, r in rows:
        vals = [r.get(k, float("nan")) for k in ("organ", "surface", *names)]
        cells = ["—" if not np.isfinite(v) else f"{v:.2f}" for v in vals]
        ok = all(0.5 <= v <= 3.0 for v in vals if np.isfinite(v))
        print(f"| {what} | {e.error_mean_mm:.2f} | " + " | ".join(cells) + f" | {'yes' if ok else 'no'} |")


if __name__ == "__main__":
    main()
