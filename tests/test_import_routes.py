"""Patient data as radiology and segmentation tools deliver it, on data navapp's meshing did
not make: phantom 0 voxelised at CT spacing (0.7 × 0.7 × 2.5 mm, an oblique grid) and
written as one NIfTI mask per structure, one NRRD label map, a DICOM SEG (highdicom), a
TotalSegmentator folder, and as STL. Every route must give the phantom's liver and vessels
within the stated tolerances; the misreadings of the issue are regression cases."""

import json

import nibabel
import numpy as np
import pytest
import surface_fixtures as sf
import trimesh
from scipy.spatial import cKDTree

from navapp.anatomy import ctcase
from navapp.anatomy.caseio import read_case
from navapp.anatomy.importer import LIVER_MAX_FACES, import_case, mask_surface
from navapp.anatomy.labelmaps import read_labelmap, structure_mask
from navapp.cli import main
from navapp.errors import InputError

# a CT's spacing and obliquity on a grid just larger than the phantom (the bench uses 512²×200)
GRID = (420, 330, 82)
NAMES = {1: "liver", 2: "portal", 3: "hepatic"}
# tolerances against the phantom's own surfaces (the STL route gives them exactly)
# (measured: liver Hausdorff 1.2-1.5 mm, volume within 0.05 %; vessel p95 0.7-0.8 mm;
# centerline median 0.6-0.65 mm, as from the phantom's own surfaces)
LIVER_HAUSDORFF_MM = 2.5  # one slice spacing
LIVER_VOLUME_REL = 0.01
VESSEL_P95_MM = 1.2  # vessel surface to the phantom's vessel surface, 95th percentile
CENTERLINE_MEDIAN_MM = 1.0  # centerline points to the phantom's centerline


_SAMPLED: dict = {}  # id(surface) → (surface, tree of its dense sample)


def _sampled_tree(b: trimesh.Trimesh, n: int, seed: int) -> cKDTree:
    """The k-d tree of ``n`` points sampled on ``b`` with ``seed``, made once per surface: the
    phantom's surfaces are the reference of 13 comparisons (0.65 CPU s a sample and tree),
    and the same seed gives the same points, so the distances are the same."""
    key = (id(b), n, seed)
    if key not in _SAMPLED:
        _SAMPLED[key] = (b, cKDTree(trimesh.sample.sample_surface(b, n, seed=seed)[0]))
    return _SAMPLED[key][1]


def _surface_distance(a: trimesh.Trimesh, b: trimesh.Trimesh, n: int = 600_000) -> np.ndarray:
    """Distances (mm) from the vertices of ``a`` to ``b`` and of ``b`` to ``a``, stacked
    (each surface sampled densely: a point-to-surface distance within ~0.4 mm). ``b`` is the
    reference (the phantom's surface, sampled once)."""
    d1, _ = _sampled_tree(b, n, 2).query(a.vertices)
    d2, _ = cKDTree(trimesh.sample.sample_surface(a, n, seed=3)[0]).query(b.vertices)
    return np.concatenate([d1, d2])


@pytest.fixture(scope="module")
def routes(phantoms, tmp_path_factory):
    """route name → (import_case kwargs) for the phantom written every way."""
    m = phantoms[0]
    folder = tmp_path_factory.mktemp("routes")
    vc = ctcase.ct_case(m, shape=GRID)
    for s, mask in vc.masks.items():
        ctcase.write_nifti(mask, vc.affine, folder / f"{s}.nii.gz")
    labels = vc.labels()
    ctcase.write_nrrd(labels, vc.affine, folder / "Segmentation.seg.nrrd", NAMES)
    ctcase.write_dicom_seg(labels, vc.affine, folder / "seg.dcm", NAMES)
    ts = folder / "totalsegmentator"
    ts.mkdir()
    ctcase.write_nifti(vc.masks["liver"], vc.affine, ts / "liver.nii.gz")
    ctcase.write_nifti(vc.masks["portal"], vc.affine, ts / "portal_vein_and_splenic_vein.nii.gz")
    ctcase.write_nifti(np.zeros(GRID, np.uint8), vc.affine, ts / "spleen.nii.gz")  # one of 117 others
    tumours = np.zeros(GRID, np.uint8)
    for t in m.targets:
        tumours |= ctcase.voxelise(t.surface, vc.affine, GRID).astype(np.uint8)
    ctcase.write_nifti(tumours, vc.affine, ts / "liver_tumor.nii.gz")
    for s in ("liver", "portal", "hepatic"):
        ctcase.write_stl(getattr(m, s), folder / f"{s}.stl")
    return folder, vc, {
        "nifti": dict(liver=folder / "liver.nii.gz", portal=folder / "portal.nii.gz",
                      hepatic=folder / "hepatic.nii.gz"),
        "nrrd": dict(labelmap=folder / "Segmentation.seg.nrrd"),
        "dicom_seg": dict(labelmap=folder / "seg.dcm"),
        "dicom_seg_segment": dict(liver=f"{folder / 'seg.dcm'}:liver"),  # one segment by its name
        "stl": dict(liver=folder / "liver.stl", portal=folder / "portal.stl", hepatic=folder / "hepatic.stl"),
    }


@pytest.fixture(scope="module")
def imported(routes, tmp_path_factory):
    folder, _, kinds = routes
    out = {}
    for name, kw in kinds.items():
        case_dir = tmp_path_factory.mktemp(f"case-{name}")
        rep = import_case(case_dir, overwrite=True, **kw)
        out[name] = (read_case(case_dir), rep)
    return out


@pytest.mark.parametrize("route", ["nifti", "nrrd", "dicom_seg", "dicom_seg_segment", "stl"])
def test_every_route_gives_the_phantoms_liver(phantoms, imported, route):
    m = phantoms[0]
    case, rep = imported[route]
    liver = case.preop.liver
    d = _surface_distance(liver, m.liver)
    assert d.max() < LIVER_HAUSDORFF_MM, f"{route}: Hausdorff {d.max():.2f} mm"
    assert liver.volume == pytest.approx(m.liver.volume, rel=LIVER_VOLUME_REL)
    assert len(liver.faces) <= max(LIVER_MAX_FACES, len(m.liver.faces))
    assert rep.frame == ("RAS" if route == "nifti" else "LPS")


@pytest.mark.parametrize("route", ["nifti", "nrrd", "dicom_seg", "stl"])
def test_every_route_gives_the_phantoms_vessels(phantoms, imported, route):
    m = phantoms[0]
    case, _ = imported[route]
    for v in ("portal", "hepatic"):
        got = case.preop.vessel(v)
        d = _surface_distance(got, getattr(m, v))
        assert np.percentile(d, 95) < VESSEL_P95_MM, f"{route} {v}: p95 {np.percentile(d, 95):.2f} mm"
        cl, ref = case.preop.centerline(v), m.centerline(v)
        dc, _ = cKDTree(ref.points).query(cl.points)
        assert np.median(dc) < CENTERLINE_MEDIAN_MM, f"{route} {v}: centerline median {np.median(dc):.2f} mm"


def test_totalsegmentator_folder_is_recognised(phantoms, routes, tmp_path):
    folder, _, _ = routes
    rep = import_case(tmp_path / "case", labelmap=folder / "totalsegmentator")
    text = "\n".join(rep.lines)
    assert "liver.nii.gz is the liver" in text and "portal_vein_and_splenic_vein.nii.gz is the portal" in text
    case = read_case(tmp_path / "case")
    assert case.preop.portal is not None and case.preop.hepatic is None
    assert case.preop.liver.volume == pytest.approx(phantoms[0].liver.volume, rel=LIVER_VOLUME_REL)
    # liver_tumor.nii.gz: one target per piece, the phantom's two tumours
    got = sorted(case.preop.targets, key=lambda t: -t.volume_ml)
    want = sorted(phantoms[0].targets, key=lambda t: -t.volume_ml)
    assert [t.name for t in got] == ["liver_tumor_1", "liver_tumor_2"]
    for g, w in zip(got, want, strict=True):
        assert np.linalg.norm(g.centre - w.centre) < 1.0
        assert g.volume_ml == pytest.approx(w.volume_ml, rel=0.1)


# ---------------------------------------------------------------- regression cases of the issue

def test_a_vessel_mask_given_as_the_liver_is_refused(routes, tmp_path):
    folder, _, _ = routes
    with pytest.raises(InputError, match=r"portal\.nii\.gz: is not liver-shaped: it fills \d+ % of its convex hull"):
        import_case(tmp_path / "case", liver=folder / "portal.nii.gz")


def test_liver_and_vessel_masks_swapped_are_refused(routes, tmp_path):
    folder, _, _ = routes
    with pytest.raises(InputError, match=r"portal\.nii\.gz: is not liver-shaped"):
        import_case(tmp_path / "case", liver=folder / "portal.nii.gz", portal=folder / "liver.nii.gz")


def test_a_repeated_flag_is_one_line_not_a_silent_drop(routes, tmp_path, capsys):
    folder, _, _ = routes
    code = main(["--quiet", "import", "--liver", str(folder / "liver.nii.gz"), "--liver", str(folder / "portal.nii.gz"),
                 "--out", str(tmp_path / "case")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--liver given 2 times" in err[0]
    assert not (tmp_path / "case").exists()


def test_a_structure_given_twice_is_refused(routes, tmp_path):
    folder, _, _ = routes
    with pytest.raises(InputError, match=r"gives the liver .* but it was also given as .*liver\.nii\.gz"):
        import_case(tmp_path / "case", liver=folder / "liver.nii.gz", labelmap=folder / "Segmentation.seg.nrrd")


def test_a_large_label_map_surface_is_decimated_and_checked_not_refused(routes):
    """The marching-cubes surface of a CT-spaced liver has hundreds of thousands of
    triangles (the issue's was refused at 75k): decimated to the stated size, then the
    self-intersection test runs on it."""
    from navapp.anatomy.cleanup import clean_surface

    folder, _, _ = routes
    lm = read_labelmap(folder / "liver.nii.gz")
    sm = structure_mask(lm, 1)
    raw = mask_surface(sm, 0.1, 10 ** 9, smooth_iterations=0)  # no decimation
    assert len(raw.faces) > 75_000
    mesh = mask_surface(sm, 2.5, LIVER_MAX_FACES)
    assert len(mesh.faces) <= LIVER_MAX_FACES
    # decimated less, as the was (1.5 mm: 90k triangles, some of them large): the
    # former candidate-pair cap refused exactly this surface; now it is checked
    fine = mask_surface(sm, 1.5, 10 ** 9)
    assert len(fine.faces) > 75_000
    clean, _ = clean_surface(fine, folder / "liver.nii.gz", what="liver surface")
    assert len(clean.faces) == len(fine.faces)


def test_self_intersection_is_checked_on_a_100k_triangle_stl(phantoms, tmp_path):
    from navapp.anatomy.cleanup import clean_surface
    from navapp.anatomy.importer import read_any_surface

    big = phantoms[0].liver.subdivide()  # 231k triangles
    assert len(big.faces) > 100_000
    big.export(tmp_path / "big.stl")
    clean, _ = clean_surface(read_any_surface(tmp_path / "big.stl"), tmp_path / "big.stl", what="liver surface")
    assert len(clean.faces) == len(big.faces)
    bad = sf.self_intersecting(big)  # one vertex pulled through the opposite side
    with pytest.raises(InputError, match=r"bad\.stl: liver surface is self-intersecting"):
        clean_surface(bad, tmp_path / "bad.stl", what="liver surface")


def test_empty_absent_label_and_singular_affine_are_one_line(routes, tmp_path):
    folder, vc, _ = routes
    ctcase.write_nifti(np.zeros((20, 20, 20), np.uint8), vc.affine, tmp_path / "empty.nii.gz")
    with pytest.raises(InputError, match=r"empty\.nii\.gz: is empty"):
        import_case(tmp_path / "c1", liver=tmp_path / "empty.nii.gz")
    with pytest.raises(InputError, match=r"liver\.nii\.gz: has no voxel with label 7 \(labels present: 1\)"):
        import_case(tmp_path / "c2", liver=f"{folder / 'liver.nii.gz'}:7")
    with pytest.raises(InputError, match=r"Segmentation\.seg\.nrrd: has no segment named 'spleen'"):
        import_case(tmp_path / "c3", liver=f"{folder / 'Segmentation.seg.nrrd'}:spleen")
    img = nibabel.load(str(folder / "liver.nii.gz"))
    A = img.affine.copy()
    A[:3, 2] = A[:3, 0]  # two axes the same: no volume
    nibabel.save(nibabel.Nifti1Image(np.asarray(img.dataobj), A), str(tmp_path / "flat.nii.gz"))
    with pytest.raises(InputError, match=r"flat\.nii\.gz: its affine \(voxel → mm\) is singular") as err:
        import_case(tmp_path / "c4", liver=tmp_path / "flat.nii.gz")
    assert "\n" not in str(err.value)


def test_masks_of_another_grid_are_refused_with_the_offset(routes, tmp_path):
    folder, vc, _ = routes
    moved = vc.affine.copy()
    moved[:3, 3] += [0.3, 0.0, 0.0]  # 0.3 mm: a resampled mask, or another scan
    ctcase.write_nifti(vc.masks["portal"], moved, tmp_path / "portal.nii.gz")
    with pytest.raises(InputError, match=r"portal\.nii\.gz: is not on the voxel grid of liver\.nii\.gz: its voxels "
                                         r"lie up to 0\.\d+ mm off that grid"):
        import_case(tmp_path / "case", liver=folder / "liver.nii.gz", portal=tmp_path / "portal.nii.gz")


def test_a_vessel_mostly_outside_the_liver_is_refused(phantoms, routes, tmp_path):
    folder, vc, _ = routes
    portal = phantoms[0].portal.copy()
    portal.apply_translation([0.0, 90.0, 0.0])  # 9 cm anterior: not this liver's vein
    # the same lattice, 100 voxels wider on each side along j (a larger field of view)
    wide = (GRID[0], GRID[1] + 200, GRID[2])
    A = ctcase.grid_affine(phantoms[0].liver.bounds.mean(0), shape=wide)
    ctcase.write_nifti(ctcase.voxelise(portal, A, wide), A, tmp_path / "portal.nii.gz")
    with pytest.raises(InputError, match=r"portal\.nii\.gz: \d+ % of the portal surface lies outside the liver"):
        import_case(tmp_path / "case", liver=folder / "liver.nii.gz", portal=tmp_path / "portal.nii.gz")


def test_cli_label_map_route_prints_stage_times(routes, tmp_path, capsys):
    folder, _, _ = routes
    assert main(["--quiet", "import", "--liver", str(folder / "liver.nii.gz"), "--out", str(tmp_path / "case")]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["frame"] == "RAS"
    assert {"read", "marching_cubes", "smoothing", "decimation", "cleanup", "regions"} <= set(out["seconds"])
