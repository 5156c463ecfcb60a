"""The tracked stylus as a data source (``simulation/sources/stylus.py``): in every scene, on
the scene's own random stream, with the cache and session keys and the data it had before
it was one (the pinned figures are main's at 560e262, docs/decisions/sources.md, "session 34")."""

import numpy as np
import pytest

from navapp.anatomy.caseio import read_case
from navapp.errors import InputError
from navapp.features import STYLUS
from navapp.simulation.scene import demo_scene, parse_scene
from navapp.simulation.scenedata import case_key, scene_key
from navapp.simulation.simulate import simulate
from navapp.simulation.sources import features_of, registered
from navapp.simulation.sources.ius import IusSpec
from navapp.simulation.sources.stylus import StylusSpec

SMALL = {"name": "small", "seed": 4, "anatomy": {"phantom": 0},
         "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.1}, "ius": {"planes": 2},
         "effects": [{"kind": "tracking_noise", "sd_mm": 0.4}, {"kind": "dropout", "fraction": 0.2}]}


def test_the_stylus_is_a_source_in_every_scene():
    stylus = registered()["stylus"]
    assert stylus.always and not registered()["laparoscope"].always
    assert features_of("stylus") == STYLUS
    plain = parse_scene({"name": "p", "anatomy": {"phantom": 0}})  # no [stylus] table: its defaults
    assert plain.sources == {"stylus": StylusSpec(), "ius": IusSpec()}
    patch = parse_scene({"name": "p", "stylus": {"pattern": "patch", "at": [1, 2, 3], "points": 50}})
    assert patch.sources["stylus"] == StylusSpec(pattern="patch", points=50, patch_at=(1.0, 2.0, 3.0))


@pytest.mark.parametrize("table, words", [
    ({"coverage": 0}, "stylus.coverage must be in (0, 1]"),
    ({"coverage": "most"}, "stylus.coverage must be a float"),
    ({"pattern": "zigzag"}, "stylus.pattern must be \"swaths\" or \"patch\""),
    ({"pattern": "patch"}, "needs stylus.at"),
    ({"at": [1, 2]}, "stylus.at must be three numbers"),
    ({"points": 5}, "stylus.points must be between 10 and 100000"),
    ({"speed": 2}, "unknown key stylus.speed (known: coverage, pattern, points, at)"),
    (3, "[stylus] must be a table"),
])
def test_a_bad_stylus_table_is_one_line(table, words):
    with pytest.raises(InputError) as e:
        parse_scene({"name": "p", "stylus": table})
    assert words in str(e.value) and "\n" not in str(e.value)


def test_scenes_keep_their_cache_and_session_keys():
    # a changed key would simulate every cached scene again and orphan every saved session
    demo = demo_scene()
    demo.source = None
    assert (scene_key(demo), case_key(demo)) == ("1eafe192d68d818c", "85571fec3be83b9c")
    patch = parse_scene({"name": "p", "stylus": {"pattern": "patch", "at": [1, 2, 3], "points": 50}})
    patch.source = None
    assert case_key(patch) == "219a0737a908de9d"


def test_the_stylus_draws_what_it_drew_before_it_was_a_source(cache_root, tmp_path):
    report = simulate(parse_scene(SMALL), tmp_path / "c", cache_root)
    assert report["stylus"] == {"coverage_of_anterior": 0.16,
                                "points": {"anterior": 442, "ridge_left": 27, "ridge_right": 85}}
    # the planes draw after the stylus on the scene's stream: they see the stream as it left it
    assert report["planes"] == [{"portal_contour": 63}, {"portal_contour": 124, "posterior": 45}]
    intraop = read_case(tmp_path / "c").intraop
    np.testing.assert_allclose(intraop["anterior"][0], [119.4794944208, 32.8546528772, 56.280835262], atol=1e-6)
    np.testing.assert_allclose(intraop["posterior"][0], [-74.4587252982, 34.0692118236, 33.6643252889], atol=1e-6)
