"""Write the local-load study scenes ``navapp/scenes/tool<p>-<x>.toml`` (3 livers × 8).

    python scripts/make_tool_scenes.py [--out DIR]
    python scripts/make_tool_scenes.py --held-out DIR   # a second draw, never used to set a margin
    python scripts/make_tool_scenes.py --held-out DIR --draw 2   # a third (tooldraw2_<p>-<x>)
    python scripts/make_tool_scenes.py --held-out DIR --draw 3 --coverage 0.2 0.65   # patches of 5–15 %


Each liver gets the same eight kinds of case; only where the tool presses and where the
data lie are drawn (seeded) from that liver's own surface, so the scenes are reproducible
and the draw is written into each file. The kinds vary what navapp's other scenes never
did: the load (a tool alone, no gravity; a prescribed dent or a pressure that bends the lobe),
its footprint (10–25 mm radius) and depth (20–60 mm), linear and neo-Hookean truth, three
kinds of support, partial surface data that
cover the indentation or miss it, and data pre-aligned or in an offset tracker frame.
"""

import argparse
from pathlib import Path

import numpy as np

from navapp.anatomy.phantom import make_phantom

OUT = Path(__file__).resolve().parents[1] / "navapp" / "scenes"

# kind: (site, load, large, radius_mm, depth_mm, supports, data, offset (deg, mm) or None, E Pa)
KINDS = {
    "a": ("anterior", "displacement", False, 15.0, 30.0, "ligaments", "covers", None, 5000.0),
    "b": ("anterior", "pressure", False, 15.0, 30.0, "bare_area", "misses", None, 5000.0),
    "c": ("inferior", "displacement", False, 20.0, 40.0, "posterior", "covers", None, 5000.0),
    "d": ("anterior", "pressure", True, 25.0, 45.0, "ligaments", "covers", None, 14000.0),
    "e": ("anterior", "pressure", False, 10.0, 20.0, "bare_area", "covers", (10.0, 15.0), 5000.0),
    "f": ("inferior", "pressure", True, 12.0, 25.0, "bare_area", "covers", (5.0, 10.0), 3000.0),
    "g": ("anterior", "displacement", False, 20.0, 60.0, "posterior", "covers", None, 8000.0),
    "h": ("anterior", "pressure", False, 15.0, 35.0, "ligaments", "swaths", None, 5000.0),
}
SITE = {"anterior": (1, 0.3), "inferior": (2, -0.5)}


def site_points(liver, site):
    axis, threshold = SITE[site]
    n = liver.vertex_normals
    on = n[:, axis] > threshold if threshold > 0 else n[:, axis] < threshold
    return liver.vertices[on]


def main(out=OUT, prefix="tool", draw=100, seed=0, coverage=None):
    """``draw`` seeds where the tools and data lie, ``seed`` each scene's own noise; the
    study's scenes are (100, 0). A held-out set draws again with other seeds and another
    name, so its cases cannot be mistaken for the ones the guards' margins were set on.
    ``coverage`` (lo, hi): each partial scan's share of the anterior surface drawn uniformly
    from it (its own seeded stream, so the sites drawn are those without it); else 0.3."""
    out.mkdir(parents=True, exist_ok=True)
    for p in range(3):
        liver = make_phantom(p).liver
        rng = np.random.default_rng(draw + p)
        share = np.random.default_rng(10_000 + draw + p)
        front = site_points(liver, "anterior")
        for x, (site, load, large, radius, depth, supports, data, offset, E) in KINDS.items():
            pts = site_points(liver, site)
            # keep tools off the outermost rim, where a footprint half hangs over the edge
            centre = pts.mean(0)
            inner = pts[np.linalg.norm(pts - centre, axis=1) < np.percentile(np.linalg.norm(pts - centre, axis=1), 70)]
            at = inner[rng.integers(len(inner))]
            if data == "covers":
                patch = at + rng.normal(scale=8.0, size=3)
            else:
                far = front[np.linalg.norm(front - at, axis=1) > 90.0]
                patch = far[rng.integers(len(far))]
            lines = [
                f"# Local-load study scene (scripts/make_tool_scenes.py): a tool presses {depth:g} mm into the {site}",
                f"# surface of phantom {p} ({radius:g} mm footprint, {load}, {'neo-Hookean' if large else 'linear'} "
                f"truth, no gravity), the liver held at its {supports} supports;",
                "# " + ("the usual stylus swaths" if data == "swaths" else
                        f"one partial surface scan of 500 points that {data} the indentation") +
                (f", in a tracker frame offset by {offset[0]:g} deg / {offset[1]:g} mm." if offset else
                 ", already in the preoperative frame."),
                f'name = "{prefix}{p}-{x}"', f"seed = {seed + 10 * p + ord(x) - ord('a')}", "",
                "[anatomy]", f"phantom = {p}", "",
                "[deformation]", "gravity = false", f'supports = "{supports}"', 'release = "N"',
                f"large = {'true' if large else 'false'}", "mesh_edge_mm = 3.5", f"truth_E_pa = {E:g}", "",
                "[tool]", f'site = "{site}"', "at = [" + ", ".join(f"{v:.1f}" for v in at) + "]",
                f"radius_mm = {radius:g}", f"depth_mm = {depth:g}", f'load = "{load}"', "",
                "[stylus]",
            ]
            if data == "swaths":
                lines += ["coverage = 0.2"]
            else:
                c = 0.3 if coverage is None else float(share.uniform(*coverage))
                lines += ['pattern = "patch"', "points = 500", f"coverage = {round(c, 2):g}",
                          "at = [" + ", ".join(f"{v:.1f}" for v in patch) + "]"]
            lines += ["", "[ius]", "planes = 16"]
            if offset:
                lines += ["", "[[effects]]", 'kind = "tracker_offset"', f"rotation_deg = {offset[0]:g}",
                          f"translation_mm = {offset[1]:g}"]
            (out / f"{prefix}{p}-{x}.toml").write_text("\n".join(lines) + "\n")
            print(out / f"{prefix}{p}-{x}.toml")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT, metavar="DIR",
                    help="where the study's own scenes go (default navapp/scenes; a test writes them elsewhere "
                         "and holds them to the committed ones)")
    ap.add_argument("--held-out", type=Path, metavar="DIR",
                    help="write a held-out set (tooltest<p>-<x>.toml, other draw and noise seeds) into DIR")
    ap.add_argument("--draw", type=int, default=1, metavar="K",
                    help="which held-out draw (1: tooltest*, the first; K > 1: tooldrawK_*, drawn from "
                         "seeds 500 + 100 (K - 1) and noise seeds 1000 K; a draw judges a rule only until "
                         "it has been looked at)")
    ap.add_argument("--coverage", type=float, nargs=2, metavar=("LO", "HI"),
                    help="draw each partial scan's share of the anterior surface uniformly from [LO, HI] "
                         "(default 0.3, about 7 %% of the whole liver surface)")
    args = ap.parse_args()
    if args.draw < 1:
        ap.error("--draw is 1 or more")
    if args.coverage is not None and not 0.0 < args.coverage[0] <= args.coverage[1] <= 1.0:
        ap.error("--coverage LO HI: 0 < LO <= HI <= 1")
    if args.held_out:
        prefix = "tooltest" if args.draw == 1 else f"tooldraw{args.draw}_"
        main(args.held_out, prefix, draw=500 + 100 * (args.draw - 1), seed=1000 * args.draw, coverage=args.coverage)
    else:
        main(args.out)
