"""The viewer's live path alone: one ``LiveRegistration`` as the app runs it, on the frames of
``navapp bench live`` (which interleaves eight variants frame by frame). One JSON line.

    python notes/scripts/live_alone.py [VARIANT] [FRAMES]
    python notes/scripts/live_alone.py default 40
"""

import json
import statistics
import sys
import time

import numpy as np

import navapp.evaluation.live_bench as lb
from navapp.registration.live import LiveRegistration
from navapp.registration.pipeline import prepare, register
from navapp.simulation.levels import data_level
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import load_scene_data, segment_frame

variant = sys.argv[1] if len(sys.argv) > 1 else "default"
frames = int(sys.argv[2]) if len(sys.argv) > 2 else 40
sd = load_scene_data(demo_scene(), edge=lb.EDGE_MM)
base = data_level(sd.case_dir, "S+planes", planes=range(3), case=sd.case)
model, _ = prepare(sd.case, lb.EDGE_MM, lb.K)
live = LiveRegistration(model, base, **lb.VARIANTS[variant])
live.last = register(model, base)
ms = []
for i, pose in enumerate(lb._poses(sd, 3, frames, 8)):
    feats = segment_frame(sd, 5000 + i, pose)
    if not feats:
        continue
    t = time.perf_counter()
    live.update(feats)
    ms.append(1000 * (time.perf_counter() - t))
print(json.dumps({"variant": variant, "median_ms": round(statistics.median(ms), 2),
                  "p90_ms": round(float(np.percentile(ms, 90)), 2),
                  "split_share": round(float(np.mean(live.split)), 2),
                  "after_first_ten_median_ms": round(statistics.median(ms[10:]), 2)}))
