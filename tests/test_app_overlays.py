"""The 2D view's overlay geometry: a mesh cut by the image plane, in pixels, against
trimesh's own plane section of the same mesh (another library's answer)."""

import numpy as np
import trimesh

from navapp.app.view2d.overlays import section_pixels
from navapp.geometry.transforms import probe_pose
from navapp.simulation.probe import Probe, tracker_to_pixels


def segment_set(px):
    """Segments as an order-free set of rounded (c0, r0, c1, r1)."""
    out = set()
    for a, b in np.round(px, 6):
        out.add(tuple(a) + tuple(b) if tuple(a) <= tuple(b) else tuple(b) + tuple(a))
    return out


def test_section_pixels_match_trimesh_mesh_plane():
    probe = Probe()
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=25.0)
    mesh.apply_translation([3.0, -2.0, 40.0])
    # a tilted probe above the sphere, looking down into it; its plane cuts the sphere off-centre
    T = probe_pose([0.0, 4.0, 0.0], lateral=[1.0, 0.1, 0.0], depth=[0.05, 0.1, 1.0])
    got = section_pixels(probe, T, mesh.vertices, mesh.faces)
    ref = trimesh.intersections.mesh_plane(mesh, T[:3, 1], T[:3, 3])  # (S, 2, 3) tracker mm
    c, r, off = tracker_to_pixels(probe, T, ref.reshape(-1, 3))
    assert np.abs(off).max() < 1e-9
    ref_px = np.column_stack([c, r]).reshape(-1, 2, 2)
    assert len(got) == len(ref_px) > 50
    assert segment_set(got) == segment_set(ref_px)
    # the section is a circle of the radius the plane's offset from the centre allows
    d = abs((mesh.centroid - T[:3, 3]) @ T[:3, 1])
    pts = got.reshape(-1, 2) * probe.spacing_mm
    radius = np.linalg.norm(pts - pts.mean(0), axis=1)
    assert abs(radius.mean() - np.sqrt(25.0 ** 2 - d ** 2)) < 0.3


def test_a_mesh_far_from_the_image_gives_nothing():
    probe = Probe()
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    mesh.apply_translation([0.0, 300.0, 40.0])  # 300 mm in front of the plane
    T = probe_pose([0.0, 0.0, 0.0], lateral=[1.0, 0.0, 0.0], depth=[0.0, 0.0, 1.0])
    assert section_pixels(probe, T, mesh.vertices, mesh.faces).shape == (0, 2, 2)
