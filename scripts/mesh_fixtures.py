"""The any-liver fixture table: each test surface through the front door (clean-up, then
the mesher chain) at a given edge; one row per fixture: meshed (method, nodes, minimum
dihedral, seconds) or refused (the one line a user would read).

    python scripts/mesh_fixtures.py [EDGE_MM] [WORD ...]   (only fixtures whose name has a WORD)
"""

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import surface_fixtures as sf  # noqa: E402

from navapp.anatomy.cleanup import clean_surface  # noqa: E402
from navapp.anatomy.meshing import mesh_liver  # noqa: E402
from navapp.anatomy.phantom import make_phantom  # noqa: E402
from navapp.errors import NavappError  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("edge", nargs="?", type=float, default=4.0, help="target edge length, mm")
ap.add_argument("words", nargs="*", metavar="WORD", help="only the fixtures whose name has one of these")
args = ap.parse_args()
edge = args.edge
phantom = make_phantom(0).liver
sharp = sf.sharp_ridged_liver()
fixtures = {
    "phantom 0": lambda: phantom,
    "sharp-ridged (plane cut, no rounding)": lambda: sharp,
    "other generator (7k vertices, decimated)": sf.other_generator_liver,
    "very uneven triangles (0.1-12 mm)": sf.uneven_liver,
    "thin lobe (6 mm)": sf.thin_lobe_liver,
    "genus 1 (a tunnel)": sf.genus_one_liver,
    "inward winding": lambda: sf.inward(phantom),
    "0.2 mm closed speck": lambda: sf.with_speck(phantom),
    "unmerged STL triangles": lambda: sf.unmerged(phantom),
    "a hole": lambda: sf.with_hole(phantom),
    "two livers": lambda: sf.two_livers(phantom),
    "self-intersecting": lambda: sf.self_intersecting(phantom),
}
print(f"| fixture (edge {edge:g} mm) | outcome | method | nodes | min dihedral ° | seconds |")
print("|---|---|---|---|---|---|")
words = args.words
for name, make in fixtures.items():
    if words and not any(w in name for w in words):
        continue
    surface = make()
    t0 = time.perf_counter()
    try:
        clean, report = clean_surface(surface, Path(f"{name}.stl"), what="liver surface")
        _, q = mesh_liver(clean, edge)
        fixes = "; ".join(report.lines()) or "nothing to repair"
        print(f"| {name} | meshed ({fixes}) | {q['method']} | {q['nodes']} | {q['min_dihedral_deg']:.1f} | "
              f"{time.perf_counter() - t0:.0f} |", flush=True)
    except NavappError as exc:
        print(f"| {name} | refused: `{exc}` | | | | {time.perf_counter() - t0:.0f} |", flush=True)
