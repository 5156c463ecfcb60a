"""Time the live-view target distances on phantom 0's two tumours (median of many calls).

    /work/venv/bin/python notes/scripts/time_target_distances.py

Random stylus tips within 40 mm of a tumour and random 64 × 80 mm image rectangles
near them (navapp's probe: 256 × 320 px at 0.25 mm); each call covers both targets.
"""

import time

import numpy as np

from navapp.anatomy.phantom import make_phantom
from navapp.geometry.targets_distance import ImagePlane, plane_distances, plane_sections, tip_distances


def median_ms(fn, args, repeat=3):
    t = []
    for a in args:
        t0 = time.perf_counter()
        for _ in range(repeat):
            fn(*a)
        t.append((time.perf_counter() - t0) / repeat * 1000)
    return float(np.median(t)), float(np.percentile(t, 95))


def main():
    targets = make_phantom(0).targets
    rng = np.random.default_rng(0)
    c = np.array([t.centre for t in targets])
    tips = [(c[i % 2] + rng.normal(size=3) * 20, targets) for i in range(200)]
    planes = []
    for i in range(200):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        origin = c[i % 2] + rng.normal(size=3) * 20 - q[:, 1] * 40
        planes.append((ImagePlane(origin, q[:, 0], q[:, 1], 255 * 0.25, 319 * 0.25), targets))
    print("targets:", ", ".join(f"{t.name} {len(t.surface.faces)} faces, {t.diameter_mm:.1f} mm" for t in targets))
    for name, fn, args in (("tip_distances", tip_distances, tips), ("plane_distances", plane_distances, planes),
                           ("plane_sections", plane_sections, planes)):
        med, p95 = median_ms(fn, args)
        print(f"{name:16s} median {med:.2f} ms, 95th percentile {p95:.2f} ms (both targets, {len(args)} poses)")


if __name__ == "__main__":
    main()
