"""easyWand's own calibration file, `*_easyWandData.mat` (easyWand 5-6, MATLAB v5/v7): the `easyWandData` struct's
DLT coefficients (`coefs`, 11 x cameras, the table easyWand exports as `*_dltCoefs.csv`), the lenses it optimised
(`nlin`: k1 k2 t1 t2 k3 per camera, its profile's columns; `nlin_est`, the profile it started from, where `nlin` is
absent) and the image sizes (`imageWidth`, `imageHeight`). The coefficients go through the DLT path
(`sfm/calibration_dlt.py`) as a `*_dltCoefs.csv` would.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dynrecon.errors import InputError
from sfm.calibration_dannce import load_mat

log = logging.getLogger(__name__)

VARIABLE = "easyWandData"
LENS_COLUMNS = 5  # k1 k2 t1 t2 k3, per camera
V73_FIX = (
    "save it again in MATLAB as a v7 file (save(name, 'easyWandData', '-v7')), or export easyWand's DLT coefficients"
)


@dataclass(kw_only=True)
class EasyWand:
    coefficients: np.ndarray  # (N, 11) L1..L11 per camera
    lenses: np.ndarray | None  # (N, 5) k1 k2 t1 t2 k3 in the tool's pixels, or None
    sizes: list[tuple[int, int]] | None  # (width, height) per camera, or None


def is_easywand(path: Path) -> bool:
    """A MATLAB file holding easyWand's `easyWandData` struct (by its name, else by its variables)."""
    if path.suffix.lower() != ".mat" or not path.is_file():
        return False
    if "easywanddata" in path.name.lower():
        return True
    import scipy.io

    try:
        return any(name == VARIABLE for name, _, _ in scipy.io.whosmat(str(path)))
    except Exception:  # not a MATLAB v5 file (v7.3, or another format): not this reader's
        return False


def read_easywand(path: Path) -> EasyWand:
    """The file's cameras (read once per file version: import reads the coefficients and the sizes apart)."""
    stat = path.stat()
    return _read(str(path), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=8)
def _read(name: str, mtime_ns: int, size: int) -> EasyWand:
    path = Path(name)
    data = load_mat(path, V73_FIX, squeeze_me=True, struct_as_record=False, variable_names=[VARIABLE])
    if VARIABLE not in data:
        raise InputError(path, f"holds no {VARIABLE} struct", fix="give easyWand's *_easyWandData.mat")
    wand = data[VARIABLE]
    coefs = getattr(wand, "coefs", None)
    table = _numbers(path, coefs, "coefs")
    if table is None or table.ndim != 2 or table.shape[0] != 11 or table.shape[1] < 1:
        shape = "missing" if table is None else "x".join(map(str, table.shape))
        raise InputError(path, f"{VARIABLE}.coefs is {shape}, not 11 x cameras", fix="calibrate in easyWand again")
    cameras = table.shape[1]
    lenses = None
    for name in ("nlin", "nlin_est"):
        values = _numbers(path, getattr(wand, name, None), name)
        if values is None:
            continue
        lenses = _lens_table(values, cameras)
        if lenses is not None:
            break
        log.warning(
            "%s: %s.%s holds %s values, not %d per camera of %d: the lenses are not read from it (give --profile)",
            path,
            VARIABLE,
            name,
            "x".join(map(str, values.shape)),
            LENS_COLUMNS,
            cameras,
        )
    widths = _numbers(path, getattr(wand, "imageWidth", None), "imageWidth")
    heights = _numbers(path, getattr(wand, "imageHeight", None), "imageHeight")
    sizes = None
    if widths is not None and heights is not None and widths.size == heights.size == cameras:
        sizes = [(int(w), int(h)) for w, h in zip(widths.ravel(), heights.ravel(), strict=True)]
    return EasyWand(coefficients=table.T.copy(), lenses=lenses, sizes=sizes)


def _lens_table(values: np.ndarray, cameras: int) -> np.ndarray | None:
    """(N, 5) k1 k2 t1 t2 k3 per camera from easyWand's vector (camera after camera) or a table of a row or a column
    per camera; None where the shape fits neither or cannot tell them apart (5 x 5)."""
    if values.ndim == 1 and values.size == LENS_COLUMNS * cameras:
        return values.reshape(cameras, LENS_COLUMNS)
    if values.ndim == 2 and values.shape != (LENS_COLUMNS, LENS_COLUMNS):
        if values.shape == (cameras, LENS_COLUMNS):
            return values
        if values.shape == (LENS_COLUMNS, cameras):
            return values.T.copy()
    return None


def _numbers(path: Path, value: Any, name: str) -> np.ndarray | None:
    """A field as a float array (None where absent or empty); not numbers or not finite: a one-line error."""
    if value is None:
        return None
    try:
        array = np.atleast_1d(np.asarray(value, dtype=float))
    except (TypeError, ValueError):
        raise InputError(path, f"{VARIABLE}.{name} is not numbers", fix="calibrate in easyWand again") from None
    if not array.size:
        return None
    if not np.all(np.isfinite(array)):
        raise InputError(path, f"{VARIABLE}.{name} holds NaN or infinity", fix="calibrate in easyWand again")
    return array


__all__ = ["EasyWand", "is_easywand", "read_easywand"]
