"""Which part of the demo's scene an idle tab's frame costs: one server, one tab, the scene
changed between measuring windows through viser's public handles (issue 50, item 7). A probe,
not a test.

    python notes/scripts/tab_frame_parts.py [ROUNDS] [VARIANT ...]

Runs ``navapp serve --edge $EDGE --k $K`` (default 12 and 12) on the demo in this process (cache: $NAVAPP_CACHE or a
temporary one), opens one 1366 x 768 tab in headless Chromium, collects the sweep and runs
"Rigid" (the scene of a click in ``tab_latency.py``: preoperative and registered surfaces, the
data, the error dots; $RUNS: other buttons in turn, comma-separated, e.g. "Rigid,Deformable (all
data)"), prints how far the registered surfaces the tab is sent lie from the state's own, then
ROUNDS times goes through the variants in turn (alternated), each
applied, settled 2 s, and measured over 6 s idle: this browser's CPU seconds per frame drawn
(WebGL clears; viser redraws once a second) and the GPU process's share. Prints medians.

Variants: ``base``; ``hide:LAYER`` (a Layers-panel layer's nodes hidden; ``hide:all`` every
layer); ``dec:N[:LAYER]`` (meshes of more than N triangles decimated to N, of one layer
or all); ``far:F`` (the camera F times as far from what it looks at); ``toon5``/``toon3``/
``flat`` (every mesh's material); ``lights:none``/``lights:ambient``/``lights:hemi``/
``lights:one`` (viser's default lights replaced); ``opaque`` (the preoperative vessels and
targets opaque); ``square`` (the point clouds drawn as squares); ``noshadow`` (meshes neither
cast nor receive shadows); ``nopoll`` (the 2D view's page stops polling the server); ``fetchonly`` (it polls
but sets nothing from the answer).
"""
import os
import statistics
import sys
import tempfile
import threading
import time

os.environ.setdefault("NAVAPP_CACHE", tempfile.mkdtemp())
import psutil  # noqa: E402
from playwright.sync_api import sync_playwright  # noqa: E402

from navapp.app.panels import layers as layers_mod  # noqa: E402

PANELS: list = []
PAGE: list = []  # the tab's page, for the variants made in the browser
_init = layers_mod.LayersPanel.__init__


def _record(self, *a, **k):
    _init(self, *a, **k)
    PANELS.append(self)


layers_mod.LayersPanel.__init__ = _record
COUNT = """
window.__gl = 0; window.__calls = [];
const orig = HTMLCanvasElement.prototype.getContext;
HTMLCanvasElement.prototype.getContext = function(...a) {
  const ctx = orig.apply(this, a);
  if (ctx && (a[0] === 'webgl2' || a[0] === 'webgl') && !ctx.__wrapped) {
    ctx.__wrapped = true;
    const clear = ctx.clear.bind(ctx);
    ctx.clear = (m) => { if (m & ctx.COLOR_BUFFER_BIT) { window.__gl++; window.__calls = []; } clear(m); };
    for (const [name, idx] of [['drawElements', 1], ['drawArrays', 2], ['drawElementsInstanced', 1],
                               ['drawArraysInstanced', 2]]) {
      const f = ctx[name].bind(ctx);
      ctx[name] = (...args) => {
        window.__calls.push([name, args[0], args[idx], name.includes('Instanced') ? args[args.length - 1] : 1]);
        return f(...args);
      };
    }
  }
  return ctx;
};
"""


def meshes(panel):
    from viser._scene_handles import MeshHandle

    return [n for nodes in panel.nodes.values() for n in nodes if isinstance(n, MeshHandle)]


def clouds(panel):
    from viser._scene_handles import PointCloudHandle

    return [n for nodes in panel.nodes.values() for n in nodes if isinstance(n, PointCloudHandle)]


def variant(name, panel, server):
    """Apply ``name``; returns a function undoing it."""
    scene = server.scene
    if name == "base":
        return lambda: None
    if name == "hide:all":
        for nodes in panel.nodes.values():
            for n in nodes:
                n.visible = False
        return panel.apply_visibility
    if name.startswith("far:"):  # the camera moved away from what it looks at: the scene drawn smaller
        cam = panel.view.client.camera
        pos, at = cam.position, cam.look_at
        cam.position = at + (pos - at) * float(name[4:])
        cam.look_at = at

        def back():
            cam.position = pos
            cam.look_at = at
        return back
    if name.startswith("dec:"):  # dec:N[:LAYER]: meshes of more than N triangles drawn decimated to N
        import trimesh

        parts = name.split(":")
        budget = int(parts[1])
        ms = [m for m in meshes(panel) if len(m.faces) > budget
              and (len(parts) < 3 or any(m is n for n in panel.nodes[parts[2]]))]
        old = [(m.vertices, m.faces) for m in ms]
        with server.atomic():
            for m in ms:
                small = trimesh.Trimesh(m.vertices, m.faces).simplify_quadric_decimation(face_count=budget)
                m.vertices, m.faces = small.vertices.astype("float32"), small.faces.astype("uint32")

        def restore():
            with server.atomic():
                for m, (v, f) in zip(ms, old, strict=True):
                    m.vertices, m.faces = v, f
        return restore
    if name == "nopoll":  # the 2D view's page stops asking the server for its state (every POLL_MS)
        frame = next(f for f in PAGE[0].frames if "/us" in f.url or f.parent_frame is not None)
        frame.evaluate("window.__st = window.setTimeout; window.setTimeout = (f, t) => 0")
        return lambda: frame.evaluate("window.setTimeout = window.__st; poll()")
    if name == "fetchonly":  # the 2D view's page polls, but only fetches (its answer read, nothing set)
        frame = next(f for f in PAGE[0].frames if "/us" in f.url or f.parent_frame is not None)
        frame.evaluate("""() => { window.__st = window.setTimeout; window.__on = true;
            window.setTimeout = (f, t) => 0;
            const loop = async () => { if (!window.__on) return;
                const r = await fetch(url("/us/state?v=" + encodeURIComponent(etag) + "&dpr=" + window.devicePixelRatio));
                await r.text(); window.__st(loop, POLL); };
            window.__st(loop, POLL); }""")
        return lambda: frame.evaluate("window.__on = false; window.setTimeout = window.__st; poll()")
    if name.startswith("hide:"):
        nodes = panel.nodes[name[5:]]
        for n in nodes:
            n.visible = False
        return panel.apply_visibility
    if name in ("toon5", "toon3"):
        ms = meshes(panel)
        for m in ms:
            m.material = name
        return lambda: [setattr(m, "material", "standard") for m in ms]
    if name == "flat":
        ms = meshes(panel)
        for m in ms:
            m.flat_shading = True
        return lambda: [setattr(m, "flat_shading", False) for m in ms]
    if name == "noshadow":
        ms = meshes(panel)
        for m in ms:
            m.cast_shadow, m.receive_shadow = False, False
        return lambda: [(setattr(m, "cast_shadow", True), setattr(m, "receive_shadow", True)) for m in ms]
    if name == "opaque":
        ms = [m for m in panel.nodes["Preoperative vessels"] + panel.nodes["Targets"] if hasattr(m, "opacity")]
        old = [m.opacity for m in ms]
        for m in ms:
            m.opacity = None
        return lambda: [setattr(m, "opacity", o) for m, o in zip(ms, old, strict=True)]
    if name == "square":
        cs = clouds(panel)
        for c in cs:
            c.point_shape = "square"
        return lambda: [setattr(c, "point_shape", "circle") for c in cs]
    if name.startswith("lights:"):
        kind = name[7:]
        scene.configure_default_lights(enabled=False, cast_shadow=False)
        added = []
        if kind == "ambient":
            added.append(scene.add_light_ambient("/probe_lights/a", intensity=2.5))
        elif kind == "hemi":
            added.append(scene.add_light_hemisphere("/probe_lights/h", intensity=2.5))
        elif kind == "one":
            added.append(scene.add_light_ambient("/probe_lights/a", intensity=0.8))
            added.append(scene.add_light_directional("/probe_lights/d", intensity=2.5,
                                                     wxyz=(1.0, 0.0, 0.0, 0.0), cast_shadow=False))

        def undo():
            for a in added:
                a.remove()
            scene.configure_default_lights(enabled=True, cast_shadow=False)
        return undo
    raise SystemExit(f"unknown variant {name}")


if __name__ == "__main__":
    from navapp import cli

    rounds = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    names = sys.argv[2:] or ["base", "hide:Preoperative liver", "hide:Registered liver"]
    port = 8941
    w = tempfile.mkdtemp()
    edge, k = os.environ.get("EDGE", "12"), os.environ.get("K", "12")
    threading.Thread(target=cli.main, args=(["serve", "--port", str(port), "--edge", edge, "--k", k,
                                             "--session", w + "/sess"],), daemon=True).start()
    time.sleep(3)
    res: dict[str, list[tuple[float, float]]] = {n: [] for n in names}
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox"])
        pg = b.new_page(viewport={"width": 1366, "height": 768})
        pg.add_init_script(COUNT)
        PAGE.append(pg)
        for _ in range(600):
            try:
                pg.goto(f"http://127.0.0.1:{port}")
                break
            except Exception:
                time.sleep(1)
        pg.get_by_text("Ready.").first.wait_for(timeout=900_000)
        if os.environ.get("STATE", "run") == "run":
            pg.get_by_role("button", name="Collect the whole sweep now").click(timeout=60_000)
            time.sleep(3)
            rows = pg.evaluate("document.querySelectorAll('table tr').length")
            for run in os.environ.get("RUNS", "Rigid").split(","):
                pg.get_by_role("button", name=run).click(timeout=60_000)
                t0 = time.time()
                while pg.evaluate("document.querySelectorAll('table tr').length") <= rows and time.time() - t0 < 600:
                    time.sleep(0.5)
                rows = pg.evaluate("document.querySelectorAll('table tr').length")
                time.sleep(2)
        time.sleep(6)
        panel, server = PANELS[-1], PANELS[-1].app.server
        if os.environ.get("STATE", "run") == "run":  # what the tab is sent against the state's surfaces
            import numpy as np
            import trimesh

            surfaces = panel.app.shown.geometry().surfaces
            for name in ("liver", "portal", "hepatic"):
                node = panel.reg.get(name)
                if node is None:
                    continue
                v, f = surfaces[name]
                whole = trimesh.Trimesh(v, f, process=False)
                drawn = trimesh.Trimesh(node.vertices, node.faces, process=False)
                out = trimesh.proximity.closest_point(whole, np.asarray(node.vertices, float))[1].max()
                back = trimesh.proximity.closest_point(drawn, np.asarray(v, float))[1]
                print(f"registered {name}: {len(node.faces)} of {len(f)} triangles drawn; drawn vertices "
                      f"within {out:.4f} mm of the surface, the surface within {back.max():.2f} mm of what is "
                      f"drawn (99th percentile {np.percentile(back, 99):.2f})", flush=True)
        procs = [q for q in psutil.Process().children(recursive=True) if "chrom" in q.name()]
        for r in range(rounds):
            for name in names:
                undo = variant(name, panel, server)
                time.sleep(2)
                cpu0 = {q.pid: sum(q.cpu_times()[:2]) for q in procs if q.is_running()}
                a = pg.evaluate("window.__gl")
                time.sleep(6)
                n = pg.evaluate("window.__gl") - a
                cpu1 = {q.pid: sum(q.cpu_times()[:2]) for q in procs if q.is_running()}
                tot = sum(cpu1[k] - cpu0[k] for k in cpu1 if k in cpu0)
                gpu = sum(cpu1[k] - cpu0[k] for k in cpu1 if k in cpu0
                          and any(c == "--type=gpu-process" for c in psutil.Process(k).cmdline()))
                if r == 0:  # one frame's draw calls: (call, mode, count, instances)
                    print(f"  {name}: {pg.evaluate('window.__calls')}", flush=True)
                if os.environ.get("SHOT") and r == 0:
                    pg.screenshot(path=f"{os.environ['SHOT']}_{name.replace(':', '_').replace(' ', '_')}.png")
                undo()
                res[name].append((tot / max(n, 1), gpu / max(tot, 1e-9)))
                print(f"round {r} {name}: {tot / max(n, 1):.3f} s/frame ({n} frames, GPU process "
                      f"{gpu / max(tot, 1e-9):.0%}), load {os.getloadavg()[0]:.1f}", flush=True)
        b.close()
    base = statistics.median(x for x, _ in res[names[0]])
    for name in names:
        m = statistics.median(x for x, _ in res[name])
        print(f"{name:40s} median {m:.3f} s/frame (x{m / base:.2f} of {names[0]}) over {len(res[name])}")
    os._exit(0)
