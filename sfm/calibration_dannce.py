"""DANNCE / Label3D calibrations (MATLAB `.mat`): a `*_dannce.mat` / `*label3d*.mat` with `params` (one struct per
camera) and `camnames`, or a folder of per-camera `*_params.mat` files (DANNCE's older demos: `cam1_params.mat`...).

Each camera struct has `K`, `r`, `t`, `RDistort` (k1, k2[, k3]) and `TDistort` (p1, p2) in MATLAB's row-vector
convention: a world point X (row, mm) projects as [X 1] [r; t] K. So OpenCV's cam_from_world is R = r', t = t',
and K = K' with the principal point moved from MATLAB's 1-based pixels to OpenCV's 0-based ones (as DANNCE moves
its labels). Checked on DANNCE's mouse_cylinder demo, whose 2D labels are its 3D labels projected: 0.00 px (see
tests/sfm/test_calibration_dannce.py). The files give no image size: the video's own size is taken.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.errors import InputError
from sfm.cameras import not_a_rotation

log = logging.getLogger(__name__)

PARAM_FILES = "*_params.mat"  # DANNCE's per-camera files in one folder
MATLAB_ORIGIN = 1.0  # MATLAB's first pixel centre is (1, 1), OpenCV's (0, 0)
FIELDS = ("K", "r", "t")
V73_FIX = "save it again in MATLAB as a v7 file: save(name, '-struct', 's', '-v7')"


def is_dannce(path: Path) -> bool:
    """A `.mat` file, or a folder holding per-camera `*_params.mat` files."""
    return path.suffix.lower() == ".mat" or (path.is_dir() and any(path.glob(PARAM_FILES)))


@dataclass(kw_only=True)
class DannceCamera:
    """One camera in OpenCV's conventions: K (3, 3) pixels, dist (5,) k1 k2 p1 p2 k3, R, t cam_from_world (m)."""

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray


def read_dannce(path: str | Path, mm: bool = True) -> list[DannceCamera]:
    """The cameras of a Label3D/DANNCE file or a folder of `*_params.mat`; translations in metres (the files' mm
    unless `mm` is False)."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob(PARAM_FILES), key=_natural)
        if not files:
            raise InputError(path, f"no DANNCE camera files ({PARAM_FILES}) in this folder")
        structs = [(f.name.removesuffix("_params.mat"), load_mat(f), f) for f in files]
    else:
        data = load_mat(path)
        if "params" in data:
            structs = [(name, s, path) for name, s in zip(_camnames(data, path), _cells(data["params"]), strict=True)]
        elif all(k in data for k in FIELDS):
            raise InputError(
                path,
                "holds one camera's parameters only",
                fix=f"give the folder that holds every camera's {PARAM_FILES} file",
            )
        else:
            raise InputError(
                path,
                "no camera parameters (`params`, or K, r and t) in this MATLAB file",
                fix="give a Label3D/DANNCE *_dannce.mat or a folder of DANNCE's cam*_params.mat files",
            )
    unit = 0.001 if mm else 1.0
    return [_camera(name, struct, where, unit) for name, struct, where in structs]


def _natural(path: Path) -> list[Any]:
    """cam2 before cam10."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", path.name)]


def load_mat(path: Path, v73_fix: str = V73_FIX, **options: Any) -> dict[str, Any]:
    """`scipy.io.loadmat(path, **options)` with a user's unreadable file as a one-line error (`v73_fix`: what to do
    with a MATLAB v7.3 file, which scipy does not read); DANNCE's files and easyWand's."""
    import scipy.io

    try:
        return scipy.io.loadmat(str(path), **options)
    except NotImplementedError:  # scipy's message for MATLAB v7.3 (HDF5) files
        raise InputError(path, "is a MATLAB v7.3 file, which is not read here", fix=v73_fix) from None
    except MemoryError:
        raise
    except Exception as error:  # a third-party parser of the user's file: any failure means unreadable
        raise InputError(path, f"not a readable MATLAB file: {error}") from None


def _cells(params: Any) -> list[dict[str, Any]]:
    """Label3D's `params` cell array of structs -> one {field: array} per camera."""
    out = []
    for cell in np.asarray(params, dtype=object).ravel():
        record = _unwrapped(cell)
        if isinstance(record, np.ndarray) and record.dtype.names is not None and record.size == 1:
            record = record.ravel()[0]
        names = getattr(getattr(record, "dtype", None), "names", None) or ()
        out.append({name: _unwrapped(record[name]) for name in names})
    return out


def _unwrapped(value: Any) -> Any:
    """MATLAB's 1x1 cells around a value, removed."""
    while isinstance(value, np.ndarray) and value.dtype == object and value.size == 1:
        value = value.ravel()[0]
    return value


def _camnames(data: dict[str, Any], path: Path) -> list[str]:
    count = np.asarray(data["params"], dtype=object).size
    if "camnames" not in data:
        log.warning("%s: no `camnames`: the cameras are named Camera1..Camera%d", path, count)
        return [f"Camera{i + 1}" for i in range(count)]
    names = [str(np.asarray(n).ravel()[0]) for n in np.asarray(data["camnames"], dtype=object).ravel()]
    if len(names) != count:
        raise InputError(path, f"{len(names)} camnames for {count} cameras in `params`")
    return names


def _camera(name: str, struct: dict[str, Any], path: Path, unit: float) -> DannceCamera:
    where = f"camera {name!r}"
    missing = [k for k in FIELDS if k not in struct]
    if missing:
        raise InputError(path, f"has no {', '.join(missing)}", where=where)
    try:
        K = np.asarray(struct["K"], dtype=float).T.copy()
        R = np.asarray(struct["r"], dtype=float).T.copy()
        t = np.asarray(struct["t"], dtype=float).reshape(3) * unit
        radial = np.asarray(struct.get("RDistort", np.zeros(2)), dtype=float).ravel()
        tangential = np.asarray(struct.get("TDistort", np.zeros(2)), dtype=float).ravel()
    except (ValueError, TypeError):
        raise InputError(
            path, "K, r, t, RDistort or TDistort is not numeric or has the wrong size", where=where
        ) from None
    if K.shape != (3, 3) or R.shape != (3, 3) or radial.size not in (2, 3) or tangential.size != 2:
        raise InputError(
            path,
            f"K {K.shape}, r {R.shape}, RDistort {radial.size} and TDistort {tangential.size} values: expected "
            "3x3, 3x3, 2 or 3, and 2",
            where=where,
        )
    if not all(np.isfinite(a).all() for a in (K, R, t, radial, tangential)):
        raise InputError(path, "K, r, t, RDistort or TDistort holds a value that is not finite", where=where)
    wrong = not_a_rotation(R)
    if wrong is not None:
        raise InputError(
            path,
            f"r is not a rotation ({wrong})",
            where=where,
            fix="r must be the orthonormal rotation of DANNCE's [X 1] [r; t] K convention",
        )
    if not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise InputError(path, "K is not MATLAB's [fx 0 0; s fy 0; cx cy 1]", where=where)
    K[0, 2] -= MATLAB_ORIGIN
    K[1, 2] -= MATLAB_ORIGIN
    dist = np.array([radial[0], radial[1], tangential[0], tangential[1], radial[2] if radial.size == 3 else 0.0])
    return DannceCamera(name=name, K=K, dist=dist, R=R, t=t)
