"""Label maps as segmentation tools write them: NIfTI (nibabel), NRRD and 3D Slicer's
``.seg.nrrd`` (pynrrd), DICOM SEG (highdicom), and folders of one mask per structure
(TotalSegmentator's output, the Decathlon's, Slicer's "export to files").

A ``LabelMap`` is an integer volume with its affine (voxel index → mm) and the frame that
affine is in; ``structure_mask`` takes one structure out of it, cropped to where it is (a
CT is 512 × 512 × 200; a liver fills a tenth of it, a vessel tree a hundredth), so every
later stage works on the crop. Every problem is one ``InputError`` line naming the file.
"""

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, short_error
from ..geometry.transforms import apply, homogeneous
from . import frames

LABELMAP_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".seg.nrrd", ".nhdr", ".dcm")
SAME_GRID_TOLERANCE = 0.1
"""Masks share one frame when every voxel centre of one lies within this fraction of the
smallest voxel spacing of a voxel centre of the other (a crop of one grid passes)."""

# structure → words that name it in a file name or a segment name (lower case)
STRUCTURE_WORDS = {"liver": ("liver",), "portal": ("portal", "pv"), "hepatic": ("hepatic", "hv")}
TOTALSEGMENTATOR = {
    "liver": "liver",
    "portal_vein_and_splenic_vein": "portal",
    "liver_tumor": "target",
}
"""TotalSegmentator's file stems (task ``total`` and ``liver_vessels``) → structure."""
TOTALSEGMENTATOR_BOTH_TREES = "liver_vessels"  # one mask of both trees: not split here


def suffix(path: Path) -> str:
    name = Path(path).name.lower()
    for s in (".seg.nrrd", ".nii.gz"):
        if name.endswith(s):
            return s
    return Path(path).suffix.lower()


def stem(path: Path) -> str:
    """The file name without its (double) suffix."""
    name = Path(path).name
    return name[: len(name) - len(suffix(path))] if suffix(path) else name


def is_dicom(path: Path) -> bool:
    """A DICOM file: the suffix, or the ``DICM`` magic at byte 128 (many have no suffix)."""
    path = Path(path)
    if suffix(path) == ".dcm":
        return True
    try:
        with path.open("rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def is_labelmap(path) -> bool:
    path = Path(path)
    return suffix(path) in LABELMAP_SUFFIXES or (path.is_file() and is_dicom(path))


@dataclass
class LabelMap:
    """A label volume: ``labels`` (I, J, K) unsigned int, or (I, J, K, S) for segments that
    may overlap (a DICOM SEG, a layered ``.seg.nrrd``: value n is layer n − 1); ``affine``
    (4, 4) voxel index → mm in ``frame``; ``names`` label value → segment name."""

    labels: np.ndarray
    affine: np.ndarray
    frame: str
    names: dict = field(default_factory=dict)
    path: Path | None = None

    @property
    def stacked(self) -> bool:
        return self.labels.ndim == 4

    @property
    def spacing(self) -> np.ndarray:
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def to_case(self) -> np.ndarray:
        """(4, 4) voxel index → mm in navapp's frame."""
        return frames.to_case(self.frame) @ self.affine

    def values(self) -> list[int]:
        """The label values present (non-zero)."""
        if self.stacked:
            return [n + 1 for n in range(self.labels.shape[3]) if self.labels[..., n].any()]
        # the labelled voxels only: sorting (np.unique) or counting (np.bincount, as intp)
        # all 52M voxels of a CT takes seconds and 0.4 GB
        flat = self.labels.ravel(order="K")  # a view in memory order (NIfTI arrays are Fortran-ordered)
        return [int(x) for x in np.unique(flat[flat != 0])]

    def mask(self, value: int) -> np.ndarray:
        if self.stacked:
            if not 1 <= value <= self.labels.shape[3]:
                return np.zeros(self.labels.shape[:3], bool)
            return self.labels[..., value - 1] > 0
        return self.labels == value


def read_labelmap(path) -> LabelMap:
    """NIfTI (RAS affine), NRRD / ``.seg.nrrd`` (``space``, ``space directions``, ``space
    origin``) or DICOM SEG (LPS, from its plane positions and orientation)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    s = suffix(path)
    if s in (".nii", ".nii.gz"):
        lm = _read_nifti(path)
    elif s in (".nrrd", ".seg.nrrd", ".nhdr"):
        lm = _read_nrrd(path)
    elif is_dicom(path):
        lm = _read_dicom_seg(path)
    else:
        raise InputError(f"not a label-map format navapp reads ({', '.join(LABELMAP_SUFFIXES)})", path)
    _check_affine(lm.affine, path)
    lm.path = path
    return lm


def _check_affine(affine: np.ndarray, path: Path):
    A = np.asarray(affine, float)
    if not np.all(np.isfinite(A)):
        raise InputError("its affine (voxel → mm) holds NaN or infinite values", path)
    spacing = np.linalg.norm(A[:3, :3], axis=0)
    det = abs(float(np.linalg.det(A[:3, :3])))
    if spacing.min() <= 0 or det < 1e-6 * float(np.prod(spacing)):
        raise InputError(f"its affine (voxel → mm) is singular (voxel sizes {', '.join(f'{x:.3g}' for x in spacing)} "
                         "mm, axes not independent): the file's geometry header is broken", path)


def _read_nifti(path: Path) -> LabelMap:
    import nibabel

    try:
        img: Any = nibabel.load(str(path))  # a spatial image (dataobj, affine)
        proxy = img.dataobj
        # the stored integers, not nibabel's float64 scaling of them (a CT-sized mask
        # would be 0.4 GB as float64); scaling is applied here only when set
        raw = np.asarray(proxy.get_unscaled()) if hasattr(proxy, "get_unscaled") else np.asarray(proxy)
        slope, inter = float(getattr(proxy, "slope", 1.0)), float(getattr(proxy, "inter", 0.0))
    except Exception as exc:  # nibabel raises many types for a bad file
        raise InputError(f"not a readable NIfTI image ({short_error(exc)})", path) from None
    if raw.ndim == 4 and raw.shape[3] == 1:
        raw = raw[..., 0]
    if raw.ndim != 3:
        raise InputError(f"is {raw.ndim}-D; a label map is 3-D", path)
    if np.isfinite(slope) and np.isfinite(inter) and (slope, inter) not in ((1.0, 0.0), (0.0, 0.0)):
        raw = raw * np.float32(slope) + np.float32(inter)
    return LabelMap(integer_labels(raw, path), np.asarray(img.affine, float), "RAS")


_NRRD_SPACES = {"left-posterior-superior": "LPS", "right-anterior-superior": "RAS", "LPS": "LPS", "RAS": "RAS",
                "left-anterior-superior": "LAS", "LAS": "LAS"}


def _is_none(row) -> bool:
    return row is None or isinstance(row, str) or bool(np.ndim(row) == 1 and np.all(np.isnan(np.asarray(row,
                                                                                                           float))))


def _read_nrrd(path: Path) -> LabelMap:
    import nrrd

    try:
        data, header = nrrd.read(str(path))
    except Exception as exc:  # pynrrd raises many types for a bad file
        raise InputError(f"not a readable NRRD file ({short_error(exc)})", path) from None
    space = header.get("space")
    if space not in _NRRD_SPACES:
        raise InputError(f"NRRD space {space!r} is not one navapp knows (LPS or RAS)", path)
    directions = list(header.get("space directions", []))
    rows = [np.asarray(r, float) for r in directions if not _is_none(r)]
    if len(rows) != 3:
        raise InputError("NRRD has no 3-D 'space directions'", path)
    if data.ndim == 4:
        # Slicer's segmentation with overlapping segments: one layer per list axis entry
        layer_axis = next(i for i, r in enumerate(directions) if _is_none(r))
        data = np.moveaxis(data, layer_axis, 0)
    elif data.ndim != 3:
        raise InputError(f"NRRD is {data.ndim}-D; a label map is 3-D", path)
    affine = homogeneous(np.column_stack(rows), np.asarray(header.get("space origin", np.zeros(3)), float))
    names: dict[Any, str] = {}
    i = 0
    while f"Segment{i}_Name" in header:
        layer = int(header.get(f"Segment{i}_Layer", 0))
        value = int(header.get(f"Segment{i}_LabelValue", i + 1))
        names[(layer, value) if data.ndim == 4 else value] = header[f"Segment{i}_Name"]
        i += 1
    if data.ndim == 4:
        # one binary layer per segment, so that overlapping segments stay whole
        layered = sorted(names.items())
        stackedarr = np.zeros((*data.shape[1:], len(layered)), np.uint8)
        for n, ((layer, value), _) in enumerate(layered):
            stackedarr[..., n] = np.asarray(data[layer]) == value
        return LabelMap(stackedarr, affine, _NRRD_SPACES[space], {n + 1: name for n, (_, name) in enumerate(layered)})
    return LabelMap(integer_labels(data, path), affine, _NRRD_SPACES[space], names)


def _read_dicom_seg(path: Path) -> LabelMap:
    try:
        import highdicom as hd
    except ImportError:
        raise InputError("reading DICOM SEG needs highdicom (pip install highdicom)", path) from None
    try:
        seg = hd.seg.segread(str(path))
    except Exception as exc:  # pydicom/highdicom raise many types for a bad or non-SEG file
        raise InputError(f"not a readable DICOM SEG ({short_error(exc)})", path) from None
    numbers = list(seg.get_segment_numbers())
    if not numbers:
        raise InputError("DICOM SEG holds no segments", path)
    try:
        vol = seg.get_volume(segment_numbers=numbers, dtype=np.uint8)
    except Exception as exc:  # frames that are not one regular 3-D grid
        raise InputError(f"DICOM SEG frames do not form one regular volume ({short_error(exc)})", path) from None
    names = {n: str(seg.get_segment_description(n).segment_label) for n in numbers}
    arr = np.asarray(vol.array)
    if arr.ndim == 3:
        arr = arr[..., None]
    # value k + 1 is layer k: renumber segment numbers in the order read
    return LabelMap(arr, np.asarray(vol.affine, float), "LPS", {k + 1: names[n] for k, n in enumerate(numbers)})


def integer_labels(data: np.ndarray, path) -> np.ndarray:
    """Whole-number labels in the smallest unsigned type that holds them."""
    data = np.asarray(data)
    if not np.issubdtype(data.dtype, np.integer):
        if data.dtype == bool:
            return data.astype(np.uint8)
        if not np.all(np.isfinite(data)) or not np.all(data == np.round(data)):
            raise InputError("holds non-integer values: a label map holds whole-number labels", path)
    lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
    if lo < 0:
        raise InputError(f"holds negative labels (down to {lo})", path)
    for t in (np.uint8, np.uint16, np.uint32):
        if hi <= np.iinfo(t).max:
            return data if data.dtype == t else data.astype(t)
    raise InputError(f"holds labels up to {hi}: too large", path)


# ---------------------------------------------------------------- one structure

@dataclass
class StructureMask:
    """One structure's voxels, cropped: ``mask`` (i, j, k) bool with one empty voxel all
    round, ``affine`` (4, 4) crop index → mm in navapp's frame, ``path`` its file."""

    mask: np.ndarray
    affine: np.ndarray
    path: Path
    label: int

    @property
    def voxel_ml(self) -> float:
        return abs(float(np.linalg.det(self.affine[:3, :3]))) / 1000.0

    @property
    def volume_ml(self) -> float:
        return float(self.mask.sum()) * self.voxel_ml


def structure_mask(lm: LabelMap, value: int) -> StructureMask:
    """The voxels of label ``value``, cropped to their bounding box plus one voxel."""
    full = lm.mask(value)
    if not full.any():
        present = lm.values()
        named = ", ".join(f"{v} ({lm.names[v]})" if v in lm.names else str(v) for v in present)
        raise InputError(f"has no voxel with label {value} (labels present: {named or 'none: the mask is empty'})",
                         lm.path)
    lo = [int(np.flatnonzero(full.any(axis=tuple(a for a in range(3) if a != k)))[0]) for k in range(3)]
    hi = [int(np.flatnonzero(full.any(axis=tuple(a for a in range(3) if a != k)))[-1]) + 1 for k in range(3)]
    crop = np.pad(full[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], 1)
    shift = homogeneous(np.eye(3), np.asarray(lo, float) - 1.0)
    assert lm.path is not None
    return StructureMask(crop, lm.to_case @ shift, lm.path, int(value))


def resolve_label(lm: LabelMap, structure: str, label: int | str | None) -> int:
    """The label value of ``structure`` in ``lm``: ``label`` (a value, or a segment name),
    else the segment named like the structure, else the only label there is."""
    present = lm.values()
    if isinstance(label, str) and not label.isdigit():
        for value, name in lm.names.items():
            if str(name).lower() == label.lower():
                return int(value)
        known = ", ".join(str(n) for n in lm.names.values()) or "none"
        raise InputError(f"has no segment named {label!r} (segments: {known})", lm.path)
    if label is not None:
        return int(label)
    for value, name in sorted(lm.names.items()):
        low = str(name).lower()
        if any(w in low.replace("_", " ").split() or low.startswith(w) for w in STRUCTURE_WORDS.get(structure, ())):
            return int(value)
    if len(present) == 1:
        return present[0]
    if not present:
        raise InputError("is empty (no voxel is labelled)", lm.path)
    named = ", ".join(f"{v} ({lm.names[v]})" if v in lm.names else str(v) for v in present)
    raise InputError(f"holds labels {named}: say which is the {structure} (e.g. --{structure} "
                     f"{lm.path.name if lm.path else 'FILE'}:{present[0]})", lm.path)


def check_same_grid(first: LabelMap, other: LabelMap):
    """Refuse ``other`` unless its voxel centres lie on ``first``'s grid (in navapp's frame):
    masks of one patient from one scan share it; a mask of another scan or a resampled one
    would put the vessels in the wrong place, silently."""
    A, B = first.to_case, other.to_case
    shape = np.asarray(other.labels.shape[:3]) - 1
    corners = np.array([[i, j, k] for i in (0, shape[0]) for j in (0, shape[1]) for k in (0, shape[2])], float)
    in_first = apply(np.linalg.inv(A), apply(B, corners))
    off_mm = np.linalg.norm((in_first - np.round(in_first)) @ A[:3, :3].T, axis=1).max()
    tol = SAME_GRID_TOLERANCE * float(min(first.spacing.min(), other.spacing.min()))
    if off_mm > tol:
        raise InputError(f"is not on the voxel grid of {first.path.name if first.path else 'the liver mask'}: "
                         f"its voxels lie up to {off_mm:.2f} mm off that grid (voxel {_fmt(other.spacing)} mm against "
                         f"{_fmt(first.spacing)} mm): masks must come from one scan", other.path)


def _fmt(v) -> str:
    return " × ".join(f"{x:.3g}" for x in v)


# ---------------------------------------------------------------- folders of masks

def recognise_folder(folder) -> tuple[dict[str, Path], list[Path], list[str]]:
    """The masks of a folder by their file names: TotalSegmentator's (``liver``,
    ``portal_vein_and_splenic_vein``, ``liver_tumor``), or any name holding liver / portal /
    hepatic. Returns (structure → file, target files, lines for the user)."""
    folder = Path(folder)
    files = sorted(p for p in folder.iterdir() if p.is_file() and is_labelmap(p))
    if not files:
        raise InputError(f"holds no label map ({', '.join(LABELMAP_SUFFIXES)})", folder)
    found: dict[str, Path] = {}
    targets: list[Path] = []
    lines: list[str] = []
    for p in files:
        name = stem(p).lower()
        if name == TOTALSEGMENTATOR_BOTH_TREES:
            lines.append(f"{p.name}: both vessel trees in one mask; not imported (give it as --portal or --hepatic "
                         "if it is one tree)")
            continue
        kind = TOTALSEGMENTATOR.get(name)
        if kind is None:
            words = name.replace("-", "_").split("_")
            if any(w.startswith(("tumor", "tumour", "lesion", "target")) for w in words):
                kind = "target"
            else:
                kind = next((s for s, ws in STRUCTURE_WORDS.items() if s != "liver" and any(w in words for w in ws)),
                            None) or ("liver" if "liver" in words and "vessel" not in name else None)
        if kind == "target":
            targets.append(p)
        elif kind is not None:
            if kind in found:
                raise InputError(f"holds two {kind} masks ({found[kind].name}, {p.name}): keep one", folder)
            found[kind] = p
    if "liver" not in found:
        raise InputError(f"has no liver mask (looked for liver.nii.gz and names with 'liver' among {len(files)} "
                         "label maps)", folder)
    return found, targets, lines
