"""How far the multi-start ICP's starts carry one plane's features of the demo scene (6 mm,
k = 20, as the browser tests run it): each feature of each plane alone, every start; prints
the planes whose farthest start places the data's centre outside the organ's sphere.

    python notes/scripts/starts_off_the_organ.py   # PYTHONPATH=<tree> to run another checkout
"""

import numpy as np

import navapp
from navapp.app.worker import viewer_options
from navapp.registration.pipeline import prepare
from navapp.registration.rigid import multi_start_icp, start_poses
from navapp.simulation.scene import demo_scene
from navapp.simulation.scenedata import load_scene_data

sd = load_scene_data(demo_scene(), None, 6.0)
model, _ = prepare(sd.case, 6.0, 20)
X = model.features["liver"].rest
reach = np.linalg.norm(X - model.centroid, axis=1).max()
print(navapp.__file__, f"organ's sphere {reach:.0f} mm")
off = 0
for plane in sd.planes:
    for name, Y in plane.features.items():
        if not len(Y):
            continue
        data = {name: np.asarray(Y)}
        starts = multi_start_icp(model, data, start_poses(model, data), viewer_options().weights)
        far = max(np.linalg.norm(s.fitted.inverse(data[name]).mean(0) - model.centroid) for s in starts)
        if far > reach:
            off += 1
            print(f"plane {plane.index} {name} ({len(Y)} points): a start {far:.3g} mm from the centroid")
print(f"{off} plane features with a start off the organ")
