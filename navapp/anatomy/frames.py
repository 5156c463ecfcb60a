"""Anatomical frames of imported data and their conversion to navapp's.

navapp's preoperative frame is "LAS": +x toward the patient's left, +y anterior, +z
superior, millimetres (the phantoms' frame; the simulator's anterior surface and the
automatic labels rely on +y being anterior). Clinical files come in RAS (NIfTI, 3D Slicer's
scene) or LPS (DICOM, NRRD, and 3D Slicer's default for exported STL/OBJ surfaces). Each
conversion is a diagonal sign flip; a flip of one axis mirrors, so triangle winding must be
reversed with it.
"""

import numpy as np

from ..errors import NavappError

CASE_FRAME = "LAS"
FRAMES = ("LAS", "LPS", "RAS")
_SIGNS = {"LAS": (1, 1, 1), "LPS": (1, -1, 1), "RAS": (-1, 1, 1)}


def to_case(frame: str) -> np.ndarray:
    """(4, 4) homogeneous transform taking ``frame`` coordinates to navapp's (LAS)."""
    frame = frame.upper()
    if frame not in _SIGNS:
        raise NavappError(f"unknown frame {frame!r}; known: {', '.join(FRAMES)}")
    return np.diag([*_SIGNS[frame], 1]).astype(float)


def mirrors(matrix: np.ndarray) -> bool:
    """Whether the affine reverses orientation (then triangle winding must be reversed)."""
    return bool(np.linalg.det(matrix[:3, :3]) < 0)
