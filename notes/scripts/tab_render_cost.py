"""What one idle tab costs: Chromium's CPU seconds per frame while the viewer idles (viser
redraws once a second), counted by the WebGL clears the page makes. A probe, not a test.

    [WHICH=label] python notes/scripts/tab_render_cost.py

Starts ``navapp serve --edge 12 --k 12`` on the demo (cache: $NAVAPP_CACHE or a temporary one),
opens one 1366 x 768 tab, and twice measures 10 s of idling.
"""
import os
import subprocess
import sys
import tempfile
import time

from playwright.sync_api import sync_playwright

env = {**os.environ, "NAVAPP_CACHE": os.environ.get("NAVAPP_CACHE", tempfile.mkdtemp()), "PYTHONUNBUFFERED": "1"}
w = tempfile.mkdtemp()
logp = w + "/s.log"
proc = subprocess.Popen([sys.executable, "-m", "navapp.cli", "serve", "--port", "8933", "--edge", "12", "--k", "12",
                         "--session", w + "/sess"], stdout=open(logp, "w"), stderr=subprocess.STDOUT, env=env)
INIT = """
window.__raf = 0; window.__gl = 0;
const r = window.requestAnimationFrame.bind(window);
window.requestAnimationFrame = (cb) => r((t) => { window.__raf++; cb(t); });
const orig = HTMLCanvasElement.prototype.getContext;
HTMLCanvasElement.prototype.getContext = function(...a) {
  const ctx = orig.apply(this, a);
  if (ctx && (a[0] === 'webgl2' || a[0] === 'webgl') && !ctx.__wrapped) {
    ctx.__wrapped = true;
    const clear = ctx.clear.bind(ctx);
    ctx.clear = (m) => { window.__gl++; clear(m); };
  }
  return ctx;
};
"""
try:
    while "viewer at" not in open(logp).read():
        time.sleep(0.5)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox"])
        pg = b.new_page(viewport={"width": 1366, "height": 768})
        pg.add_init_script(INIT)
        pg.goto("http://127.0.0.1:8933")
        pg.get_by_text("Ready.").first.wait_for(timeout=900_000)
        time.sleep(5)
        import psutil

        def idle(what):
            # this browser's processes only: other Chromiums on a shared machine are not this tab's
            procs = [q for q in psutil.Process().children(recursive=True) if "chrom" in q.name()]
            cpu0 = {q.pid: sum(q.cpu_times()[:2]) for q in procs}
            a = pg.evaluate("window.__gl")
            time.sleep(10)
            cpu1 = {q.pid: sum(q.cpu_times()[:2]) for q in procs if q.is_running()}
            n = pg.evaluate("window.__gl") - a
            tot = sum(cpu1[k] - cpu0[k] for k in cpu1)
            print(f"{what}: chromium CPU {tot:.2f} s in 10 s, {n} frames, {tot/max(n,1):.3f} s/frame", flush=True)

        idle(os.environ.get("WHICH", "?"))
        time.sleep(1)
        idle(os.environ.get("WHICH", "?"))
        b.close()
finally:
    proc.terminate()
    proc.wait(20)
