"""Render the committed phantom pictures: python scripts/render_phantoms.py [OUT_DIR]."""

import argparse
from pathlib import Path

from navapp.anatomy.phantom import make_phantom
from navapp.evaluation.render import phantom_figure

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("out", nargs="?", type=Path, default=Path("docs/img"), help="folder for phantom0-2.png")
out = ap.parse_args().out
out.mkdir(parents=True, exist_ok=True)
for i in range(3):
    m = make_phantom(i)
    phantom_figure(m, out / f"phantom{i}.png", title=f"phantom {i}: {m.liver.extents[0]:.0f} × "
                   f"{m.liver.extents[1]:.0f} × {m.liver.extents[2]:.0f} mm, {m.liver.volume / 1e3:.0f} ml")
    print(out / f"phantom{i}.png")
