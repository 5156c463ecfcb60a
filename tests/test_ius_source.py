"""The tracked iUS probe as a data source (``simulation/sources/ius.py``): its preset planes in
every scene, after the stylus on the scene's own stream, and one frame at a pose chosen after
the simulation (a free plane, a live frame's automatic segmentation), with the data they gave
before they were one (the pinned figures are main's at 6c0cdb6, docs/decisions/sources.md,
"session 35")."""

import numpy as np
import pytest

from navapp.errors import InputError
from navapp.features import BY_NAME
from navapp.simulation.scene import parse_scene
from navapp.simulation.scenedata import acquire_free_plane, load_scene_data, segment_frame
from navapp.simulation.sources import features_of, registered
from navapp.simulation.sources.ius import IusSpec

SMALL = {"name": "small", "seed": 4, "anatomy": {"phantom": 0},
         "deformation": {"release": "L", "mesh_edge_mm": 10.0},
         "stylus": {"coverage": 0.1}, "ius": {"planes": 2},
         "effects": [{"kind": "tracking_noise", "sd_mm": 0.4}, {"kind": "auto_segmentation", "sd_px": 1.0}]}


def test_the_ius_planes_are_a_source_in_every_scene():
    ius = registered()["ius"]
    assert ius.always and ius.acquires_effects and ius.frame is not None and ius.report_as == "planes"
    assert list(registered())[:2] == ["stylus", "ius"]  # the order they draw on the scene's stream
    assert all(BY_NAME[f].source == "ius" for f in features_of("ius")) and "posterior" in features_of("ius")
    plain = parse_scene({"name": "p"})
    assert plain.sources["ius"] == IusSpec() and plain.planes == 16
    assert parse_scene({"name": "p", "ius": {"planes": 0}}).planes == 0


@pytest.mark.parametrize("table, words", [
    ({"planes": 17}, "ius.planes must be between 0 and 16"),
    ({"planes": -1}, "ius.planes must be between 0 and 16"),
    ({"planes": 2.5}, "ius.planes must be a int, got 2.5"),
    ({"planes": True}, "ius.planes must be a int"),
    ({"depth": 3}, "unknown key ius.depth (known: planes)"),
    (3, "[ius] must be a table"),
])
def test_a_bad_ius_table_is_one_line(table, words):
    with pytest.raises(InputError) as e:
        parse_scene({"name": "p", "ius": table})
    assert words in str(e.value) and "\n" not in str(e.value)


def test_a_frame_at_a_chosen_pose_is_what_it_was_before_it_was_a_source(cache_root, tmp_path):
    sd = load_scene_data(parse_scene(SMALL), tmp_path, edge=12.0)
    T = sd.planes[1].probe_to_tracker
    free = acquire_free_plane(sd, 100, T)
    assert {k: len(v) for k, v in free.features.items()} == {"portal_contour": 152, "posterior": 56}
    assert free.image is not None and free.image.shape == (320, 256) and int(free.image.sum()) == 4200025
    np.testing.assert_allclose(free.features["posterior"][0], [-74.338164255, 34.1679279985, 33.6376583099],
                               atol=1e-6)
    live = segment_frame(sd, 5000, T)  # the declared automatic segmentation's 1 px, its own stream
    assert {k: len(v) for k, v in live.items()} == {"portal_contour": 277, "posterior": 76}
    np.testing.assert_allclose(live["portal_contour"][0], [-78.9323398055, 24.5766750251, 26.1530481882],
                               atol=1e-6)
    sd.scene.effects[:] = [e for e in sd.scene.effects if e.kind != "auto_segmentation"]
    assert segment_frame(sd, 5000, T) == {}  # no segmentation declared: the surgeon draws


def test_a_scene_simulation_stopped_half_way_leaves_no_case_in_the_cache(cache_root, tmp_path, monkeypatch):
    # the viewer's cache swaps a simulated case in whole through ``outputs.staged`` (its one home)
    from navapp.simulation import simulate as sim
    from navapp.simulation.scenedata import case_key, simulated_case_dir

    scene = parse_scene({**SMALL, "name": "halfway", "ius": {"planes": 1}})

    def stop(*a, **k):
        raise RuntimeError("stopped while writing the planes")

    monkeypatch.setattr(sim, "write_frames", stop)
    with pytest.raises(RuntimeError):
        simulated_case_dir(scene, tmp_path)
    out = tmp_path / "scenes" / f"halfway-{case_key(scene)}"
    assert not out.exists() and [p.name for p in out.parent.iterdir()] == []
    monkeypatch.undo()
    assert simulated_case_dir(scene, tmp_path) == out and (out / "intraop" / "us" / "planes.json").is_file()
