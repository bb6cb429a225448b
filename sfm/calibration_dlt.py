"""DLT coefficient files as static cameras: DLTdv's and easyWand's `*_dltCoefs.csv`, Argus's
`*-dlt-coefficients.csv` (11 rows, one column per camera), or one camera per row of 11 numbers (a course's `.cal`).

The 11 coefficients L1..L11 map world X, Y, Z to the file's pixels u, v:
    u = (L1 X + L2 Y + L3 Z + L4) / (L9 X + L10 Y + L11 Z + 1)
    v = (L5 X + L6 Y + L7 Z + L8) / (L9 X + L10 Y + L11 Z + 1)
a projection matrix with P[2, 3] = 1: a pinhole camera with skew and two focal lengths, for undistorted pixels
(the tools keep lens distortion apart, in a camera profile, read with `--profile`: the tools' coefficients about
the profile's own principal point and focal length, taken here about the DLT's, which the calibration fitted to the
same undistorted points). Decomposed here (RQ) into K, R, t.

The file's pixels (`DltPixels`, from the tools' source; docs/formats.md), against OpenCV's (x, y), H the image
height: DLTdv 5-7 (and easyWand fed from it): u = x + 1, v = H - y (rows counted up from the bottom); Argus:
u = x, v = H - y; DLTdv 8: u = x + 1, v = y + 1; OPENCV: u = x, v = y. Rows counted from the bottom mirror the
image, so a camera's handedness tells the two apart (AUTO): with the file's pixels taken as counted from the top,
a right-handed world gives every camera a rotation, a world seen through bottom-up rows a mirror. The height is
not in the file: a bottom-up camera's principal point row is kept relative to the bottom edge
(`StaticCamera.cy_plus_height`) until the video's height is known.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import scipy.linalg

from dynrecon.errors import InputError
from dynrecon.readers import read_text
from sfm.calibration_easywand import is_easywand, read_easywand
from tracking.pixels import DltPixels

log = logging.getLogger(__name__)
_PROFILE_SAID: set[str] = set()  # files whose profile beside them was pointed out

COEFFICIENTS = 11
PLANAR_COEFFICIENTS = 8  # DLTdv 8.4's 2D DLT: a plane, not a camera
ARGUS_NAME = "-dlt-coefficients"  # Argus's file names end so; DLTdv's and easyWand's in _dltCoefs
MIRROR_X = np.diag([-1.0, 1.0, 1.0])


def is_dlt(path: Path) -> bool:
    """A DLT coefficient file by its name: DLTdv / easyWand `*dltCoefs*`, Argus `*-dlt-coefficients*`, or a text
    file with `dlt` in its name (a course's `dlt_all_cams.cal`); or easyWand's own `*_easyWandData.mat`."""
    lower = path.name.lower()
    texts = (".cal", ".csv", ".txt", ".dat")
    named = "dltcoefs" in lower or ARGUS_NAME in lower or ("dlt" in lower and lower.endswith(texts))
    return named or is_easywand(path)


def dlt_sizes(path: Path) -> list[tuple[int, int]] | None:
    """The image size (width, height) per camera where the file gives it (easyWand's .mat), else None."""
    return read_easywand(path).sizes if is_easywand(path) else None


def _number_rows(path: Path, *, headers: int | None) -> tuple[list[tuple[int, list[float]]], int]:
    """(line number, values) of every row of numbers in a text file (separated by commas, semicolons or spaces;
    blank lines and # comments skipped), and the number of header lines (with letters) before the first row: at
    most `headers` of them (None: any); any other line is a one-line error naming it."""
    rows: list[tuple[int, list[float]]] = []
    header = 0
    for number, line in enumerate(read_text(path).splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        try:
            rows.append((number, [float(f) for f in re.split(r"[,;\s]+", text) if f]))
        except ValueError:
            if not rows and (headers is None or header < headers) and any(c.isalpha() for c in text):
                header += 1
                continue
            raise InputError(path, f"{text[:40]!r} is not a row of numbers", where=f"line {number}") from None
    return rows, header


def read_dlt_coefficients(path: str | Path) -> np.ndarray:
    """(N, 11): one row of L1..L11 per camera, from either layout (a column per camera, or a row per camera)."""
    path = Path(path)
    numbered, headers = _number_rows(path, headers=1)  # an old Argus's L_1, ..., rmse
    header = headers > 0
    rows = [values for _, values in numbered]
    for number, values in numbered:
        if len(values) != len(rows[0]):
            raise InputError(
                path,
                f"{len(values)} numbers where line 1 has {len(rows[0])}",
                where=f"line {number}",
                fix="every row of a DLT file has the same number of values",
            )
    table = np.asarray(rows, dtype=float)
    if table.ndim != 2 or not table.size:
        raise InputError(path, "no DLT coefficients in the file", fix="give a *_dltCoefs.csv (11 rows, a camera each)")
    if table.shape[0] == PLANAR_COEFFICIENTS and table.shape[1] != COEFFICIENTS:
        raise InputError(path, "holds 8 coefficients per camera: a 2D (planar) DLT, which poses no camera in 3D")
    # a row per camera: 11 values, or an old Argus's 12 (an rmse column, under a header)
    by_row = (header and table.shape[1] in (COEFFICIENTS, COEFFICIENTS + 1)) or (
        table.shape[1] == COEFFICIENTS and table.shape[0] != COEFFICIENTS
    )
    if by_row:
        coefficients = table[:, :COEFFICIENTS]
    elif table.shape[0] == COEFFICIENTS and table.shape[1] != COEFFICIENTS:
        coefficients = table.T
    elif table.shape == (COEFFICIENTS, COEFFICIENTS):
        raise InputError(path, "11 rows of 11 values: a camera per column or per row cannot be told apart")
    else:
        raise InputError(
            path,
            f"a table of {table.shape[0]} x {table.shape[1]} values is no DLT file",
            fix="expected 11 rows with one column per camera (DLTdv, easyWand, Argus) or a row of 11 per camera",
        )
    if not np.all(np.isfinite(coefficients)):
        raise InputError(path, "a coefficient is NaN or infinite", fix="calibrate that camera again")
    return coefficients


def dlt_matrix(coefficients: np.ndarray) -> np.ndarray:
    """The 3x4 projection matrix of L1..L11 (11,)."""
    c = np.asarray(coefficients, dtype=float)
    return np.array([c[0:4], c[4:8], [c[8], c[9], c[10], 1.0]])


def to_opencv_matrix(P: np.ndarray, pixels: DltPixels) -> np.ndarray:
    """P (3, 4) in the file's pixels -> OpenCV's, with a bottom-up file's rows taken as counted down from row 0:
    the image height is then added to K's principal point row alone (`cy_plus_height`)."""
    # file (u, v, 1) = A (x, y, 1): OpenCV's pixels are A^-1 file's, with the height's term left out
    a_inverse = np.eye(3)
    a_inverse[0, 2] = -pixels.column_origin
    if pixels.from_bottom:
        a_inverse[1, 1] = -1.0
    elif pixels is DltPixels.DLTDV8:
        a_inverse[1, 2] = -1.0
    return a_inverse @ P


def decompose(P: np.ndarray, scene: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K (3, 3), R (3, 3), t (3,) with P ~ K [R | t], K's diagonal positive and `scene` (3,) in front of the
    camera; R is a mirror (det -1) where the world is seen mirrored (left-handed axes, or rows read the wrong
    way)."""
    K, R = scipy.linalg.rq(P[:, :3])
    signs = np.diag(np.sign(np.diag(K)))
    K, R = K @ signs, signs @ R
    scale = K[2, 2]
    K = K / scale
    t = np.linalg.solve(K, P[:, 3]) / scale
    if R[2] @ scene + t[2] < 0:  # P and -P are one DLT; the scene lies in front
        R, t = -R, -t
    return K, R, t


def scene_point(matrices: list[np.ndarray]) -> np.ndarray:
    """A world point every camera looks at: the point nearest to all optical axes (least squares), or the world
    origin (the calibration object's, in view) where the axes do not cross (one camera, parallel axes)."""
    if len(matrices) < 2:
        return np.zeros(3)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for P in matrices:
        M = P[:, :3]
        centre = -np.linalg.solve(M, P[:, 3])
        axis = M[2] / np.linalg.norm(M[2])
        projector = np.eye(3) - np.outer(axis, axis)
        A += projector
        b += projector @ centre
    if np.linalg.cond(A) > 1e8:
        return np.zeros(3)
    return np.linalg.solve(A, b)


def mirrored(P: np.ndarray, scene: np.ndarray) -> bool:
    """Whether P (OpenCV's rows direction assumed) sees a mirrored world."""
    return bool(np.linalg.det(decompose(P, scene)[1]) < 0)


def choose_pixels(path: Path, coefficients: np.ndarray, pixels: DltPixels) -> DltPixels:
    """`pixels`, or for AUTO the convention of the tool that wrote the file: for DLTdv's, easyWand's and Argus's
    files (told by their names) rows up from the bottom where the file's rows read downwards give every camera a
    mirror (easyWand 6 and Argus make their worlds right-handed), Argus's columns from 0; for other files OpenCV's
    (their world may be left-handed: a course's L-frame, then mirrored with a warning)."""
    if pixels is not DltPixels.AUTO:
        return pixels
    lower = path.name.lower()
    if "dltcoefs" not in lower and ARGUS_NAME not in lower and not is_easywand(path):
        log.info(
            "%s: pixels read as OpenCV's (rows down from the top, from 0): no DLTdv / easyWand / Argus file name; "
            "--pixels to say otherwise",
            path,
        )
        return DltPixels.OPENCV
    top_down = [to_opencv_matrix(dlt_matrix(c), DltPixels.OPENCV) for c in coefficients]
    scene = scene_point(top_down)
    mirrors = [mirrored(P, scene) for P in top_down]
    if any(mirrors) != all(mirrors):
        raise InputError(
            path,
            "its cameras disagree on which way the image rows run (some see the world mirrored): the coefficients "
            "are not of one calibration",
            fix="calibrate the cameras together again, or give --pixels for the convention of all of them",
        )
    argus = ARGUS_NAME in lower
    if all(mirrors):
        chosen = DltPixels.ARGUS if argus else DltPixels.DLTDV7
    else:
        chosen = DltPixels.OPENCV if argus else DltPixels.DLTDV8
    log.info(
        "%s: pixels read as %s's (%s; --pixels to say otherwise)",
        path,
        chosen.value,
        "rows up from the bottom: the reading in which the world is right-handed"
        if chosen.from_bottom
        else "rows down from the top: the world is right-handed so",
    )
    return chosen


PROFILE_COLUMNS = 12  # cam# f W H cx cy aspect k1 k2 t1 t2 k3


def read_profile(path: str | Path, cameras: int, pixels: DltPixels) -> list[np.ndarray]:
    """OpenCV distortion (k1, k2, p1, p2, k3) per camera from an easyWand / Argus / DLTdv camera profile (a row
    `cam# f W H cx cy aspect k1 k2 t1 t2 k3` per camera, space-separated): the coefficients the tools undistort the
    points with before their DLT (`opencv_lens`)."""
    path = Path(path)
    rows: dict[int, np.ndarray] = {}
    for number, numbers in _number_rows(path, headers=None)[0]:  # Argus's calibration CSVs have a header
        if not numbers:  # a line of separators only
            continue
        values = np.array(numbers)
        if len(values) != PROFILE_COLUMNS or not np.all(np.isfinite(values)):
            raise InputError(
                path,
                f"{len(values)} values where a camera profile has {PROFILE_COLUMNS} finite ones",
                where=f"line {number}",
                fix="a row per camera: cam# f width height cx cy aspect k1 k2 t1 t2 k3 (omnidirectional profiles "
                "are not read)",
            )
        rows[round(values[0])] = values
    missing = [c + 1 for c in range(cameras) if c + 1 not in rows]
    if missing:
        raise InputError(
            path,
            f"no row for camera {', '.join(map(str, missing))} of the DLT file's {cameras}",
            fix="give the profile written with these coefficients (a row per camera, numbered from 1)",
        )
    return [opencv_lens(rows[c + 1][7:12], pixels) for c in range(cameras)]


def opencv_lens(tool: np.ndarray, pixels: DltPixels) -> np.ndarray:
    """OpenCV's (k1, k2, p1, p2, k3) of a tool's k1 k2 t1 t2 k3 (a profile's columns, easyWand's `nlin`): in pixels
    counted up from the bottom the image's y is negated, and so is the first tangential term."""
    k1, k2, t1, t2, k3 = (float(v) for v in tool)
    return np.array([k1, k2, (-1.0 if pixels.from_bottom else 1.0) * t1, t2, k3])


def _profile_beside(path: Path) -> Path | None:
    """A camera profile next to a DLT file (easyWand's `*_profile.txt`, Argus's `*-profile.txt`), if any."""
    found = sorted(path.parent.glob("*profile*.txt"))
    return found[0] if found else None


def dlt_cameras(
    path: str | Path, pixels: DltPixels = DltPixels.AUTO, profile: str | Path | None = None
) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, bool, np.ndarray]]:
    """(name, K, R, t, cy_plus_height, dist) per camera of a DLT file, in OpenCV's conventions, t in the file's
    units (its world's), dist from the camera `profile` (none without one); cameras are named cam1, cam2... in the
    file's order. A mirrored world (left-handed axes) is turned into a right-handed one by negating its x axis,
    with a warning."""
    path = Path(path)
    wand = read_easywand(path) if is_easywand(path) else None
    coefficients = wand.coefficients if wand is not None else read_dlt_coefficients(path)
    for number, row in enumerate(coefficients, start=1):
        M = dlt_matrix(row)[:, :3]
        if abs(np.linalg.det(M)) <= 1e-12 * np.linalg.norm(M) ** 3:  # no centre, no viewing direction
            raise InputError(
                path,
                f"camera {number}'s coefficients describe no camera (their 3x3 part is singular)",
                where=f"camera {number}",
                fix="calibrate that camera again",
            )
    pixels = choose_pixels(path, coefficients, pixels)
    matrices = [to_opencv_matrix(dlt_matrix(c), pixels) for c in coefficients]
    scene = scene_point(matrices)
    decomposed = [decompose(P, scene) for P in matrices]
    mirrors = [bool(np.linalg.det(R) < 0) for _, R, _ in decomposed]
    if any(mirrors) != all(mirrors):
        raise InputError(
            path,
            f"with {pixels.value}'s pixels, cameras {', '.join(f'cam{i + 1}' for i, m in enumerate(mirrors) if m)} "
            "see the world mirrored and the others do not: the coefficients are not of one calibration",
            fix="calibrate the cameras together again",
        )
    if all(mirrors):
        log.warning(
            "%s: with %s's pixels the DLT's world axes are left-handed (a mirror image): dynrecon's world is the "
            "file's with x negated (negate the outputs' x to return to the file's axes; --pixels if the rows run "
            "the other way)",
            path,
            pixels.value,
        )
        decomposed = [(K, R @ MIRROR_X, t) for K, R, t in decomposed]
    if profile is not None:
        distortion = read_profile(profile, len(decomposed), pixels)
    elif wand is not None and wand.lenses is not None:  # the lenses easyWand optimised, in its profile's columns
        distortion = [opencv_lens(lens, pixels) for lens in wand.lenses]
    else:
        distortion = [np.zeros(5)] * len(decomposed)
        beside = _profile_beside(path)
        if beside is not None and str(path) not in _PROFILE_SAID:  # registration reads the file in several steps
            _PROFILE_SAID.add(str(path))
            log.warning(
                "%s: a camera profile lies beside it (%s): DLT coefficients are for undistorted pixels, and the "
                "points are not; give import-calibration --profile %s (run: --calibration-profile) to model the "
                "lenses (for --intrinsics, give the cameras.json that import writes)",
                path,
                beside.name,
                beside,
            )
    return [
        (f"cam{i + 1}", K, R, t, pixels.from_bottom, dist)
        for i, ((K, R, t), dist) in enumerate(zip(decomposed, distortion, strict=True))
    ]


__all__ = [
    "DltPixels",
    "decompose",
    "dlt_cameras",
    "dlt_matrix",
    "dlt_sizes",
    "is_dlt",
    "opencv_lens",
    "read_dlt_coefficients",
    "read_profile",
]
