"""CT-sized label maps from a phantom, written the way segmentation tools write them.

The importer's tests and its benchmark need data navapp's own meshing did not make: a
phantom's closed surfaces are voxelised on a CT grid (0.7 × 0.7 × 2.5 mm, 512 × 512 × 200,
an oblique affine, so no axis of the grid is an axis of the patient) by the ray-parity
inside test at each voxel centre, then written as one NIfTI mask per structure (RAS, as
TotalSegmentator and the Decathlon do), one NRRD label map (LPS), a DICOM SEG (highdicom,
with the CT series it refers to made up as headers only) or STL (LPS, as 3D Slicer exports).
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from ..geometry.transforms import apply, homogeneous
from . import frames
from .model import VESSELS
from .skeleton import inside_grid

CT_SPACING = (0.7, 0.7, 2.5)  # mm: a typical abdominal portal-venous CT
CT_SHAPE = (512, 512, 200)
CT_TILT_DEG = (8.0, 5.0, 3.0)  # rotations about z, x, y of the grid's axes against the patient's
STRUCTURES = ("liver", *VESSELS)


@dataclass
class VoxelCase:
    """Masks on one grid: ``masks`` structure → (I, J, K) uint8 (0/1), ``affine`` (4, 4)
    voxel index → mm in navapp's frame (LAS)."""

    masks: dict
    affine: np.ndarray

    def labels(self) -> np.ndarray:
        """One label map: liver 1, portal 2, hepatic 3 (vessels win where they overlap)."""
        out = np.zeros(next(iter(self.masks.values())).shape, np.uint8)
        for value, name in enumerate(STRUCTURES, start=1):
            if name in self.masks:
                out[self.masks[name] > 0] = value
        return out


def grid_affine(centre, spacing=CT_SPACING, shape=CT_SHAPE, tilt_deg=CT_TILT_DEG) -> np.ndarray:
    """(4, 4) index → mm (LAS) of a rotated, anisotropic grid whose middle voxel is ``centre``."""
    # R_z R_x R_y, angles in the order of ``tilt_deg``
    axes = Rotation.from_euler("ZXY", tilt_deg, degrees=True).as_matrix() @ np.diag(spacing)
    return homogeneous(axes, np.asarray(centre, float) - axes @ ((np.asarray(shape) - 1) / 2.0))


def voxelise(mesh: trimesh.Trimesh, affine: np.ndarray, shape) -> np.ndarray:
    """(I, J, K) bool: the voxel centres of the grid ``affine`` (index → mm) inside ``mesh``."""
    shape = np.asarray(shape, int)
    tri = apply(np.linalg.inv(affine), mesh.vertices)[np.asarray(mesh.faces)]
    # a tiny offset keeps grid lines off the surface's vertices and edges (double counts)
    tri = tri + np.array([1.234567e-4, 2.345671e-4, 3.456712e-4])
    lo = np.clip(np.floor(tri.reshape(-1, 3).min(0)).astype(int) - 1, 0, shape)
    hi = np.clip(np.ceil(tri.reshape(-1, 3).max(0)).astype(int) + 2, 0, shape)
    if np.any(hi - lo < 1) or np.any(tri.reshape(-1, 3).min(0) < 0) or np.any(tri.reshape(-1, 3).max(0) > shape - 1):
        raise ValueError("the surface does not fit in the grid")
    out = np.zeros(tuple(shape), bool)
    out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = inside_grid(tri - lo, hi - lo)
    return out


def ct_case(model, spacing=CT_SPACING, shape=CT_SHAPE, tilt_deg=CT_TILT_DEG) -> VoxelCase:
    """The liver and both vessel trees of ``model`` (a ``PreopModel``) voxelised on a CT grid
    centred on the liver."""
    A = grid_affine(model.liver.bounds.mean(0), spacing, shape, tilt_deg)
    masks = {name: voxelise(getattr(model, name), A, shape).astype(np.uint8)
             for name in STRUCTURES if getattr(model, name, None) is not None}
    return VoxelCase(masks, A)


# ---------------------------------------------------------------- writers

def write_nifti(mask: np.ndarray, affine_las: np.ndarray, path) -> Path:
    """A NIfTI (RAS affine, as nibabel and every segmentation tool write it)."""
    import nibabel

    path = Path(path)
    img = nibabel.Nifti1Image(np.asarray(mask, np.uint8), frames.to_case("RAS") @ affine_las)
    img.set_qform(img.affine, code=1)
    img.set_sform(img.affine, code=1)
    nibabel.save(img, str(path))
    return path


def write_nrrd(labels: np.ndarray, affine_las: np.ndarray, path, names: dict | None = None) -> Path:
    """An NRRD label map in LPS, with 3D Slicer's segment names when ``names`` (value → name)."""
    import nrrd

    A = frames.to_case("LPS") @ affine_las  # LAS ↔ LPS is its own inverse
    header = {"space": "left-posterior-superior", "space directions": A[:3, :3].T, "space origin": A[:3, 3],
              "encoding": "gzip"}
    for i, (value, name) in enumerate(sorted((names or {}).items())):
        header.update({f"Segment{i}_Name": name, f"Segment{i}_LabelValue": str(value), f"Segment{i}_Layer": "0"})
    nrrd.write(str(path), np.asarray(labels, np.uint8), header)
    return Path(path)


def write_stl(mesh: trimesh.Trimesh, path) -> Path:
    """An STL in LPS with 3D Slicer's ``SPACE=LPS`` in the solid name."""
    M = frames.to_case("LPS")
    lps = trimesh.Trimesh(apply(M, mesh.vertices), np.asarray(mesh.faces)[:, ::-1], process=False)
    data = trimesh.exchange.stl.export_stl(lps)
    path = Path(path)
    path.write_bytes(b"SPACE=LPS".ljust(80, b" ") + data[80:])
    return path


def write_dicom_seg(labels: np.ndarray, affine_las: np.ndarray, path, names: dict) -> Path:
    """A DICOM SEG (BINARY, one segment per label value, labels from ``names``) written by
    highdicom, referring to a CT series made up here as headers only (no pixel data):
    image columns along the grid's i axis, rows along j, one slice per k."""
    import highdicom as hd
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sr.codedict import codes
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    A = frames.to_case("LPS") @ affine_las  # DICOM's patient frame is LPS
    spacing = np.linalg.norm(A[:3, :3], axis=0)
    col_dir, row_dir = A[:3, 0] / spacing[0], A[:3, 1] / spacing[1]
    study, series, frame_uid = generate_uid(), generate_uid(), generate_uid()
    ni, nj, nk = labels.shape
    sources = []
    for k in range(nk):
        ds = Dataset()
        ds.file_meta = FileMetaDataset()
        ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds.file_meta.MediaStorageSOPClassUID = CTImageStorage
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame_uid
        ds.Modality = "CT"
        ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = "Phantom^Navapp", "NAVAPP0", "", "O"
        ds.StudyDate, ds.StudyTime, ds.StudyID, ds.AccessionNumber = "20260101", "120000", "1", ""
        ds.ReferringPhysicianName = ""
        ds.SeriesNumber, ds.InstanceNumber = 1, k + 1
        ds.Rows, ds.Columns = nj, ni
        ds.PixelSpacing = [float(spacing[1]), float(spacing[0])]  # row spacing (along j), column spacing (along i)
        ds.SliceThickness = float(spacing[2])
        ds.ImageOrientationPatient = [float(x) for x in (*col_dir, *row_dir)]
        ds.ImagePositionPatient = [float(x) for x in apply(A, np.array([[0.0, 0.0, k]]))[0]]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        sources.append(ds)
    values = sorted(names)
    descriptions = [
        hd.seg.SegmentDescription(
            segment_number=n, segment_label=names[v],
            segmented_property_category=codes.SCT.Organ if names[v] == "liver" else codes.SCT.Tissue,
            segmented_property_type=codes.SCT.Liver if names[v] == "liver" else codes.SCT.Vein,
            algorithm_type=hd.seg.SegmentAlgorithmTypeValues.MANUAL)
        for n, v in enumerate(values, start=1)]
    # frames (k, rows = j, columns = i), one binary layer per segment
    stacked = np.stack([np.transpose(labels == v, (2, 1, 0)) for v in values], axis=-1).astype(np.uint8)
    seg = hd.seg.Segmentation(
        source_images=sources, pixel_array=stacked, segmentation_type=hd.seg.SegmentationTypeValues.BINARY,
        segment_descriptions=descriptions, series_instance_uid=generate_uid(), series_number=2,
        sop_instance_uid=generate_uid(), instance_number=1, manufacturer="navapp",
        manufacturer_model_name="navapp ctcase", software_versions="1", device_serial_number="0")
    _contiguous_frames(seg, int(stacked.sum()))
    seg.save_as(str(path))
    return Path(path)


def _contiguous_frames(seg, voxels: int) -> None:
    """A 1-bit SEG's frames packed end to end, as the standard has them (PS3.5 §8.1.1) and pydicom
    and highdicom read them. highdicom 0.28 pads each frame to a whole byte when it holds fewer
    than 8 pixels, and its own reader then took the second frame's pixels from the first's
    padding (a one-voxel tumour read back empty, found by the property tests). ``voxels``: the
    segments' voxels written; the padded layout is taken only when it, and not the standard's,
    holds that many (a later highdicom that packs correctly is left alone)."""
    n = int(seg.Rows) * int(seg.Columns)
    frames = int(getattr(seg, "NumberOfFrames", 1))
    per = -(-n // 8)
    raw = np.frombuffer(seg.PixelData, np.uint8)
    if n % 8 == 0 or frames < 2 or len(raw) < frames * per:
        return
    padded = np.unpackbits(raw[:frames * per].reshape(frames, per), axis=1, bitorder="little")[:, :n]
    flat = np.unpackbits(raw, bitorder="little")[:frames * n]
    if int(padded.sum()) != voxels or int(flat.sum()) == voxels:
        return
    packed = np.packbits(padded.ravel(), bitorder="little").tobytes()
    seg.PixelData = packed + b"\0" * (len(packed) % 2)


def imported_liver(liver: trimesh.Trimesh, spacing=CT_SPACING, tilt_deg=CT_TILT_DEG) -> trimesh.Trimesh:
    """``liver`` as navapp's import of a CT label map of it gives it back: voxelised on an
    oblique grid of ``spacing`` mm, then marching cubes, smoothing and decimation
    (``importer.mask_surface``) and the import's clean-up. What a real segmentation gives:
    the voxel staircase leaves thousands of creases over 40° (Gmsh's feature lines)."""
    from .cleanup import clean_surface
    from .importer import LIVER_MAX_FACES, LIVER_SURFACE_EDGE_MM, mask_surface
    from .labelmaps import StructureMask

    reach = liver.bounds[1] - liver.bounds[0]
    shape = tuple(int(np.ceil(1.2 * float(reach.max()) / s)) + 4 for s in spacing)  # any tilt fits
    affine = grid_affine(liver.bounds.mean(0), spacing, shape, tilt_deg)
    mask = voxelise(liver, affine, shape)
    idx = np.argwhere(mask)
    lo, hi = idx.min(0), idx.max(0) + 1
    shift = homogeneous(np.eye(3), lo - 1.0)
    crop = StructureMask(np.pad(mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], 1), affine @ shift,
                         Path("liver.nii.gz"), 1)
    surface = mask_surface(crop, LIVER_SURFACE_EDGE_MM, LIVER_MAX_FACES)
    return clean_surface(surface, crop.path, closed=True, what="liver")[0]
