"""The live follower's first (cold) update on small data (issue 48, item 5): N cold
registrations of a short stretch of the replayed stylus path (1-14 consecutive points at 25 Hz)
with a live frame's automatic segmentation thinned to 0-4 points a feature, on the demo at 6 mm,
k = 20, with the viewer's options. Prints one line a registration and the count that raised.

    python notes/scripts/live_first_update_fuzz.py SEED N [CACHE]

Run with ``python -X faulthandler`` to see where a crash of the process happens.
"""

import sys
import tempfile
import traceback
from pathlib import Path

import numpy as np

from navapp.app.server import App
from navapp.app.worker import viewer_options
from navapp.registration.live import LiveRegistration
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import load_scene_data, segment_frame
from navapp.tracking.replay import script_from_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from conftest import free_port  # noqa: E402

seed, count = int(sys.argv[1]), int(sys.argv[2])
cache = Path(sys.argv[3]) if len(sys.argv) > 3 else Path(tempfile.mkdtemp())
scene = demo_scene()
script = script_from_scene(scene, transit_frames=2, edge=6.0, cache_root=cache)
app = App(scene, port=free_port(), session_dir=Path(tempfile.mkdtemp()), edge=6.0, k=20, cache_root=cache)
assert app.start().wait(900) and app.core.failed is None
model = app.core.model
sd = load_scene_data(scene, cache, 6.0)
rng = np.random.default_rng(seed)
bad = 0
for it in range(count):
    feats = segment_frame(sd, 100000 + it, script.probe_at(rng.uniform(0, script.cycle_s)))
    thin = {}
    for k, v in feats.items():
        m = int(rng.integers(0, 5))
        if m and len(v):
            thin[k] = v[rng.choice(len(v), min(m, len(v)), replace=False)]
    n = int(rng.integers(1, 15))
    i = rng.uniform(0, 1000)
    base = {"anterior": np.array([script.stylus_at(i + j / 25) for j in range(n)]).reshape(-1, 3)}
    try:
        LiveRegistration(model, base, options=viewer_options()).update(thin)
        msg = "ok"
    except Exception as e:
        bad += 1
        msg = f"{type(e).__name__}: {e}"
        traceback.print_exc()
    print(f"it={it} n={n} feats={ {k: len(v) for k, v in thin.items()} } {msg}", flush=True)
print("raised", bad)
app.server.stop()
app.view2d.stop()
