"""N tabs on one machine: where the time goes between a click on "Rigid" in the first tab and the
run's row in every tab (issue 50, item 7). A probe, not a test.

    python notes/scripts/tab_latency.py N_TABS

Starts ``navapp serve --edge 12 --k 12`` on the demo (cache: $NAVAPP_CACHE, or a temporary
one), opens N tabs in one headless Chromium, collects the sweep, then twice clicks "Rigid" in
the first tab. Prints per trial: when the page saw the pointer go down, when the server logged
the run's start and end (its action log), and when each tab's run table gained the row.
"""
import datetime
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from playwright.sync_api import sync_playwright

N = int(sys.argv[1]) if len(sys.argv) > 1 else 10
work = Path(tempfile.mkdtemp())
env = {**os.environ, "NAVAPP_CACHE": os.environ.get("NAVAPP_CACHE", str(work / "cache")), "PYTHONUNBUFFERED": "1"}
log_path, session = work / "server.log", work / "session"
port = 8931
proc = subprocess.Popen([sys.executable, "-m", "navapp.cli", "serve", "--port", str(port), "--edge", "12", "--k", "12",
                         "--session", str(session)], stdout=log_path.open("w"), stderr=subprocess.STDOUT, env=env)
ROWS = "() => document.querySelectorAll('table tr').length"


def logged(after: float) -> list[tuple[str, float]]:
    """The action log's lines after ``after`` (epoch s): (action, seconds after ``after``)."""
    out = []
    for line in (session / "actions.jsonl").read_text().splitlines():
        x = json.loads(line)
        t = datetime.datetime.fromisoformat(x["time"].replace("Z", "+00:00")).timestamp()
        if t >= after:
            out.append((x["action"], round(t - after, 2)))
    return out


try:
    t0 = time.time()
    while "viewer at" not in log_path.read_text() and time.time() - t0 < 900:
        time.sleep(0.5)
    url = re.search(r"viewer at (http://\S+)", log_path.read_text()).group(1)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox"])
        pages = []
        for _ in range(N):
            pg = b.new_page(viewport={"width": 1366, "height": 768})
            pg.goto(url)
            pages.append(pg)
        for pg in pages:
            pg.get_by_text("Ready.").first.wait_for(timeout=900_000)
        print(f"{N} tabs ready {time.time() - t0:.0f} s after the server's start", flush=True)
        p0 = pages[0]
        p0.get_by_role("button", name="Collect the whole sweep now").click(timeout=60_000)
        time.sleep(3)
        p0.evaluate("window.__down = 0; "
                    "document.addEventListener('pointerdown', () => { window.__down = Date.now(); }, true)")
        for trial in range(2):
            before = [pg.evaluate(ROWS) for pg in pages]
            tc = time.time()
            p0.get_by_role("button", name="Rigid").click(timeout=60_000)
            seen: list[float | None] = [None] * N
            while any(s is None for s in seen) and time.time() - tc < 300:
                for i, pg in enumerate(pages):
                    if seen[i] is None and pg.evaluate(ROWS) > before[i]:
                        seen[i] = round(time.time() - tc, 2)
                time.sleep(0.05)
            down = round(p0.evaluate("window.__down") / 1000 - tc, 2)
            print(f"trial {trial}: pointer down +{down} s; server {logged(tc)}; row in each tab +{seen} s", flush=True)
            time.sleep(3)
        b.close()
finally:
    proc.terminate()
    proc.wait(20)
