"""Property-based tests over every reader: whatever a file holds, it is read or refused in one
line naming the file (``InputError``), never a traceback. Few examples each (CI's budget):
hypothesis searches the space a little on every run, and its database keeps what it found."""


import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

from navapp.errors import InputError, NavappError

FAST = settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck), derandomize=False)
SLOW = settings(max_examples=8, deadline=None, suppress_health_check=list(HealthCheck))


def read_or_refused(read, path):
    """``read()``'s value, or None when it refused in one line naming ``path``."""
    try:
        return read()
    except InputError as exc:
        text = str(exc)
        assert "\n" not in text, text
        assert Path(path).name in text, text
        return None


def fresh_dir() -> Path:
    return Path(tempfile.mkdtemp(prefix="navapp-prop-"))


# ---------------------------------------------------------------- CSV points

cell = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers().map(str),
                 st.sampled_from(["", "x", "y", "z", "nan", "1e400", " 3 ", "1,5", "\ufeff1", "--1", "0x10"]),
                 st.text(max_size=4))
row = st.lists(cell, min_size=0, max_size=5).map(",".join)
csv_text = st.tuples(st.sampled_from(["", "x,y,z\n", "x,y,z,branch\n", "name,x,y,z\n", "name,x,y,z,radius_mm\n"]),
                     st.lists(row, max_size=6)).map(lambda t: t[0] + "\n".join(t[1]) + "\n")


@FAST
@given(csv_text)
def test_point_csvs_are_read_or_refused_in_one_line(text):
    from navapp.anatomy.caseio import read_csv
    from navapp.anatomy.targets import read_points_csv

    path = fresh_dir() / "anterior.csv"
    path.write_text(text)
    pts = read_or_refused(lambda: read_csv(path, ("x", "y", "z"), points=True), path)
    if pts is not None:
        assert pts.ndim == 2 and pts.shape[1] == 3 and np.isfinite(pts).all()
    cl = read_or_refused(lambda: read_csv(path, ("x", "y", "z", "branch"), integer_last=True), path)
    if cl is not None:
        assert np.isfinite(cl).all() and np.all(cl[:, 3] == np.round(cl[:, 3]))
    targets = read_or_refused(lambda: read_points_csv(path), path)
    for t in targets or []:
        assert np.isfinite(t.centre).all()


# ---------------------------------------------------------------- surfaces

def _damaged(base: trimesh.Trimesh, ops: list[str], seed: int) -> trimesh.Trimesh:
    rng = np.random.default_rng(seed)
    v, f = np.asarray(base.vertices, float).copy(), np.asarray(base.faces).copy()
    for op in ops:
        if op == "duplicate" and len(f):  # a triangle's corners stored again (STL-like)
            k = rng.integers(len(f))
            v = np.vstack([v, v[f[k]]])
            f = np.vstack([f, [len(v) - 3, len(v) - 2, len(v) - 1]])
        elif op == "degenerate" and len(f):
            k = rng.integers(len(f))
            f = np.vstack([f, [f[k, 0], f[k, 0], f[k, 1]]])
        elif op == "inverted" and len(f):
            k = rng.integers(len(f), size=max(1, len(f) // 3))
            f[k] = f[k][:, ::-1]
        elif op == "hole" and len(f) > 1:
            f = np.delete(f, rng.integers(len(f)), axis=0)
        elif op == "piece":
            f = np.vstack([f, f + len(v)])
            v = np.vstack([v, v + [200.0 * rng.uniform(0.5, 1.0), 0, 0]])
        elif op == "speck":
            s = trimesh.creation.icosphere(0, radius=0.5)
            f = np.vstack([f, s.faces + len(v)])
            v = np.vstack([v, s.vertices + v.mean(0) + 300.0])
        elif op == "repeat_face" and len(f):
            f = np.vstack([f, f[:1]])
        elif op == "flat":
            v[:, 2] = 0.0
        elif op == "nan":
            v[rng.integers(len(v))] = np.nan
        elif op == "empty":
            f = f[:0]
    return trimesh.Trimesh(v, f, process=False)


OPS = st.lists(st.sampled_from(["duplicate", "degenerate", "inverted", "hole", "piece", "speck", "repeat_face",
                                "flat", "nan", "empty"]), max_size=4)


@FAST
@given(st.sampled_from(["sphere", "box", "liverish"]), OPS, st.sampled_from(["ply", "stl", "obj", "vtk"]),
       st.integers(0, 2 ** 16))
@example("box", ["flat"], "ply", 0)  # found: a closed surface folded flat was taken as a liver of no volume
def test_damaged_surfaces_are_read_or_refused_in_one_line(shape, ops, fmt, seed):
    import meshio

    from navapp.anatomy.cleanup import clean_surface
    from navapp.anatomy.importer import read_any_surface

    base = {"sphere": lambda: trimesh.creation.icosphere(2, radius=60.0),
            "box": lambda: trimesh.creation.box([120.0, 90.0, 70.0]),
            "liverish": lambda: trimesh.creation.icosphere(2, radius=1.0).apply_scale([100.0, 70.0, 60.0])}[shape]()
    mesh = _damaged(base, ops, seed)
    path = fresh_dir() / f"liver.{fmt}"
    try:
        if fmt == "vtk":
            meshio.write(path, meshio.Mesh(mesh.vertices, [("triangle", mesh.faces)]))
        else:
            mesh.export(path, file_type=fmt)
    except Exception:  # a writer that cannot hold it (no triangles): nothing to read
        return
    read = read_or_refused(lambda: read_any_surface(path), path)
    if read is None:
        return
    for closed in (True, False):
        got = read_or_refused(lambda c=closed: clean_surface(read, path, closed=c, what="liver surface"), path)
        if got is not None:
            clean, _ = got
            assert np.isfinite(clean.vertices).all() and len(clean.faces) > 0
            if closed:
                assert clean.is_watertight and clean.volume > 0


@FAST
@given(st.binary(max_size=400), st.sampled_from(["ply", "stl", "obj", "vtk", "vtp"]))
@example(b"", "vtk")  # found: meshio printed its error and called sys.exit(1) (exit status 1, no one line)
def test_surface_files_of_garbage_are_refused_in_one_line(data, fmt):
    from navapp.anatomy.importer import read_any_surface

    path = fresh_dir() / f"liver.{fmt}"
    path.write_bytes(data)
    read_or_refused(lambda: read_any_surface(path), path)


# ---------------------------------------------------------------- masks

@st.composite
def masks(draw):
    shape = tuple(draw(st.lists(st.integers(1, 12), min_size=3, max_size=3)))
    fill = draw(st.sampled_from(["empty", "block", "two_blocks", "random"] + ["liver_and_tumour"] * 4))
    labels = np.zeros(shape, np.uint8)
    rng = np.random.default_rng(draw(st.integers(0, 2 ** 16)))
    if fill == "block":
        labels[1:-1, 1:-1, 1:-1] = draw(st.integers(1, 3))
    elif fill == "two_blocks":
        labels[: shape[0] // 2] = 1
        labels[shape[0] // 2 + 1:] = 1
    elif fill == "random":
        labels = rng.integers(0, 3, shape).astype(np.uint8)
    elif fill == "liver_and_tumour":
        labels[:, :, :] = 1
        labels[[0, -1]] = labels[:, [0, -1]] = labels[:, :, [0, -1]] = 0
        labels[: max(2, shape[0] // 3), : max(2, shape[1] // 3)] = 2  # a tumour at the border, disjoint
    spacing = draw(st.sampled_from([[12.0, 12.0, 20.0]] * 3 + [[15.0, 10.0, 25.0]] * 2 + [[0.0, 1.0, 1.0]]
                                   + [[-8.0, 20.0, 20.0], [0.5, 0.5, 0.5]]))
    angle = draw(st.floats(-np.pi, np.pi))
    A = np.eye(4)
    c, s = np.cos(angle), np.sin(angle)
    A[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag(spacing)
    A[:3, 3] = draw(st.lists(st.floats(-500, 500), min_size=3, max_size=3))
    return labels, A


@SLOW
@given(masks(), st.sampled_from(["nii.gz", "nrrd"]), st.sampled_from(["labelmap", "liver", "liver_and_target"]))
# found: a mask of a few voxels (56 triangles) was decimated "to 200" and the decimator raised
@example((np.pad(np.ones((1, 2, 2), np.uint8), ((0, 2), (0, 0), (0, 0)))[[0, 1, 0]], np.diag([0.5, 0.5, 0.5, 1.0])),
         "nii.gz", "labelmap")
def test_masks_are_imported_or_refused_in_one_line(mask, fmt, route):
    import nibabel
    import nrrd

    from navapp.anatomy.importer import import_case, read_labelmap

    labels, A = mask
    folder = fresh_dir()
    path = folder / f"seg.{fmt}"
    try:
        if fmt == "nii.gz":
            nibabel.save(nibabel.Nifti1Image(labels, A), str(path))
        else:
            nrrd.write(str(path), labels, {"space": "left-posterior-superior", "space directions": A[:3, :3].T,
                                           "space origin": A[:3, 3]})
    except Exception:  # the writer refuses it (nibabel: a singular affine): no such file to read
        return
    if read_or_refused(lambda: read_labelmap(path), path) is None:
        return
    kwargs = {"labelmap": {"labelmap": path, "labels": {"liver": 1}},
              "liver": {"liver": f"{path}:1"},
              "liver_and_target": {"liver": f"{path}:1", "targets": [f"{path}:2"]}}[route]
    try:
        try:
            import_case(folder / "case", **kwargs)
            event("imported")
        except InputError as exc:
            event(f"refused: {str(exc).split(': ', 1)[-1][:30]}")
            raise
        except NavappError as exc:  # a refusal of the arguments, not of the file: still one line
            event("refused (arguments)")
            assert "\n" not in str(exc)
    except InputError:
        read_or_refused(lambda: import_case(folder / "case2", **kwargs), path)


# ---------------------------------------------------------------- DICOM SEG

SEG_NAMES = {1: "liver", 2: "tumour", 3: "portal"}


def _write_seg(labels, A, path) -> bool:
    """``labels`` written as a DICOM SEG by highdicom (``ctcase``, the import benchmark's
    writer); False where the writer itself refuses the grid (no file to read then)."""
    from navapp.anatomy.ctcase import write_dicom_seg

    present = {int(v) for v in np.unique(labels) if v}
    try:
        write_dicom_seg(labels, A, path, {v: SEG_NAMES[v] for v in present})
    except Exception:  # highdicom refuses it (no segment, a singular grid): not a file navapp is given
        return False
    return path.is_file()


@SLOW
@given(masks(), st.sampled_from(["read", "labelmap", "liver_and_target"]))
# found by this test in CI: frames of fewer than 8 pixels, each padded to a byte by highdicom's
# writer (``ctcase._contiguous_frames``), read back with the tumour empty
@example((np.array([[[2, 1]]], np.uint8), np.diag([12.0, 12.0, 20.0, 1.0])), "read")
@example((np.ones((3, 1, 4), np.uint8), np.diag([1.0, 1.0, 1.0, 1.0])), "read")
def test_dicom_segs_are_imported_or_refused_in_one_line(mask, route):
    """DICOM SEGs of any grid and labels (empty, several pieces, a tumour disjoint from the
    liver, oblique, 0.5 mm to 25 mm voxels): read, imported or refused in one line."""
    from navapp.anatomy.importer import import_case, read_labelmap

    labels, A = mask
    folder = fresh_dir()
    path = folder / "seg.dcm"
    if not _write_seg(labels, A, path):
        return
    lm = read_or_refused(lambda: read_labelmap(path), path)
    if lm is None or route == "read":
        if lm is not None:  # what was written is what is read, segment by segment
            for v, name in lm.names.items():
                assert name in SEG_NAMES.values()
                want = next(k for k, n in SEG_NAMES.items() if n == name)
                assert lm.mask(v).sum() == (labels == want).sum()
        return
    kwargs = {"labelmap": {"labelmap": path}, "liver_and_target": {"liver": f"{path}:liver",
                                                                 "targets": [f"{path}:tumour"]}}[route]
    try:
        import_case(folder / "case", **kwargs)
    except InputError as exc:
        text = str(exc)
        assert "\n" not in text and ("seg.dcm" in text or "case" in text), text
    except NavappError as exc:  # a refusal of the arguments, not of the file: still one line
        assert "\n" not in str(exc)


@pytest.fixture(scope="module")
def seg_bytes():
    """A valid DICOM SEG of a liver and a disjoint tumour (the public sets' convention)."""
    labels = np.zeros((8, 7, 5), np.uint8)
    labels[1:-1, 1:-1, 1:-1] = 1
    labels[1:3, 1:3, 1:-1] = 2
    path = fresh_dir() / "seg.dcm"
    assert _write_seg(labels, np.diag([12.0, 12.0, 20.0, 1.0]), path)
    return path.read_bytes()


@FAST
@given(st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.binary(min_size=1, max_size=8)), min_size=1,
                max_size=4), st.one_of(st.none(), st.floats(0, 1)))
def test_damaged_dicom_segs_are_refused_in_one_line(seg_bytes, patches, cut):
    """A real DICOM SEG with bytes overwritten anywhere (header, segment sequence, plane
    positions, pixel data) or cut short: read, or refused in one line naming the file."""
    from navapp.anatomy.importer import read_labelmap

    data = bytearray(seg_bytes)
    for where, new in patches:
        at = int(where * len(data))
        data[at:at + len(new)] = new
    if cut is not None:
        data = data[:int(cut * len(data))]
    path = fresh_dir() / "seg.dcm"
    path.write_bytes(bytes(data))
    lm = read_or_refused(lambda: read_labelmap(path), path)
    if lm is not None:
        assert lm.labels.ndim in (3, 4) and np.isfinite(lm.affine).all()


# ---------------------------------------------------------------- case.toml, scene TOML

toml_value = st.recursive(st.one_of(st.integers(-5, 5), st.floats(allow_nan=False, width=32), st.booleans(),
                                    st.text(max_size=5)),
                          lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                                       max_size=3), max_leaves=6)


@FAST
@given(st.one_of(st.dictionaries(st.sampled_from(["name", "units", "scene", "frame", "other", "k"]), toml_value,
                                 max_size=4).map(lambda d: ("dict", d)),
                 st.text(max_size=60).map(lambda t: ("text", t))))
def test_case_toml_is_read_or_refused_in_one_line(liver_case, content):
    import tomli_w

    from navapp.anatomy.caseio import read_case

    kind, value = content
    folder = fresh_dir() / "case"
    (folder / "preop").mkdir(parents=True)
    (folder / "preop/liver.ply").write_bytes(liver_case)
    text = tomli_w.dumps(value) if kind == "dict" else value
    (folder / "case.toml").write_text(text)
    read_or_refused(lambda: read_case(folder), folder / "case.toml")


@pytest.fixture(scope="module")
def liver_case():
    """A liver-sized ellipsoid as PLY bytes."""
    m = trimesh.creation.icosphere(3, radius=1.0).apply_scale([100.0, 70.0, 60.0])
    return m.export(file_type="ply")


def _mutate(data, path, value):
    """``data`` (nested dicts) with the key at ``path`` set to ``value`` (None: deleted)."""
    import copy

    out = copy.deepcopy(data)
    node = out
    for key in path[:-1]:
        if not isinstance(node.get(key), dict):
            node[key] = {}
        node = node[key]
    if value is None:
        node.pop(path[-1], None)
    else:
        node[path[-1]] = value
    return out


SCENE_KEYS = st.sampled_from([("name",), ("seed",), ("anatomy", "phantom"), ("anatomy", "case"),
                              ("deformation", "release"), ("deformation", "gravity_tilt_deg"),
                              ("deformation", "large"), ("deformation", "mesh_edge_mm"),
                              ("deformation", "truth_E_pa"), ("stylus", "coverage"), ("ius", "planes"),
                              ("effects",), ("extra",), ("deformation", "unknown")])


@FAST
@given(st.lists(st.tuples(SCENE_KEYS, st.one_of(st.none(), toml_value,
                                                st.lists(st.dictionaries(st.sampled_from(["kind", "sd_mm", "ms",
                                                                                          "sd_px"]),
                                                                         toml_value, max_size=3), max_size=2))),
                max_size=3))
@example([(("effects",), [{"kind": []}])])  # found in CI: an unhashable kind was a TypeError
def test_scene_toml_is_read_or_refused_in_one_line(changes):
    import tomllib

    import tomli_w

    import navapp
    from navapp.simulation.scene import load_scene

    data = tomllib.loads((navapp.scene_dir() / "demo.toml").read_text())
    for key, value in changes:
        data = _mutate(data, key, value)
    path = fresh_dir() / "scene.toml"
    try:
        path.write_text(tomli_w.dumps(data))
    except Exception:  # not expressible as TOML (a list of mixed kinds): nothing to read
        return
    read_or_refused(lambda: load_scene(path), path)


# ---------------------------------------------------------------- OpenIGTLink

@st.composite
def igtl_messages(draw):
    import pyigtl

    kind = draw(st.sampled_from(["TRANSFORM", "IMAGE", "STRING", "POINT", "NOPE", "garbage"]))
    device = draw(st.sampled_from(["StylusTipToReference", "ProbeToReference", "Image_Reference", "Other", ""]))
    ts = draw(st.floats(0, 4e9, allow_nan=False))
    if kind == "TRANSFORM":
        m = np.array(draw(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=16,
                                   max_size=16))).reshape(4, 4)
        if draw(st.booleans()):
            m[3] = [0, 0, 0, 1]
        msg = pyigtl.TransformMessage(m, device_name=device, timestamp=ts)
    elif kind == "IMAGE":
        shape = tuple(draw(st.lists(st.integers(1, 6), min_size=2, max_size=3)))
        msg = pyigtl.ImageMessage(np.zeros(shape, np.uint8), device_name=device, timestamp=ts)
    elif kind == "STRING":
        msg = pyigtl.StringMessage(draw(st.text("abc ", max_size=10)), device_name=device)
    else:
        msg = None
    if msg is not None:
        raw = msg.pack()
    else:
        raw = struct.pack(">H12s20sIIQQ", 2, kind.encode()[:12], device.encode()[:20], 0, 0, 0, 0)
        raw += draw(st.binary(max_size=80))
    cut = draw(st.sampled_from([None, "body", "flip"]))
    head, body = raw[:58], raw[58:]
    if cut == "body":
        body = body[: len(body) // 2]
    elif cut == "flip" and body:
        k = draw(st.integers(0, len(body) - 1))
        body = body[:k] + bytes([body[k] ^ 0xFF]) + body[k + 1:]
    return head, body


@FAST
@given(st.lists(igtl_messages(), min_size=1, max_size=4))
def test_openigtlink_messages_are_taken_or_skipped_never_raised(messages):
    from navapp.tracking.client import TrackingClient, parse_header
    from navapp.tracking.config import TrackingConfig

    client = TrackingClient(TrackingConfig(port=1))  # never started: messages are fed by hand
    for head, body in messages:
        fields = parse_header(head)
        if fields is None:
            continue
        fields["body_size"] = len(body)
        client._on_message(fields, body)
    assert set(client.status()) is not None


@FAST
@given(st.binary(min_size=58, max_size=58))
def test_any_58_bytes_are_a_header_or_none(raw):
    from navapp.tracking.client import parse_header

    fields = parse_header(raw)
    assert fields is None or fields["body_size"] >= 0



