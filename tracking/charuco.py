"""ChArUco board corners as tracks: every inner corner OpenCV's aruco module finds in every frame of each video.

The board comes from caliscope's `charuco.toml` (or the `[charuco]` table of its `config.toml`): `columns`, `rows`
(squares), `dictionary` (an OpenCV predefined dictionary name such as DICT_4X4_1000), `square_size_override_cm`
(the printed square edge; without it the square fills `board_width` x `board_height` in `units`), `aruco_scale`
(marker edge / square edge) and `inverted` (printed white on black: frames are inverted, 255 - gray, before
detection) and `thickness_cm` (a two-sided board's substrate). The board is OpenCV's
`CharucoBoard((columns, rows), ...)`, as caliscope builds it, so corner ids and
positions are the same as caliscope's: corner i at `getChessboardCorners()[i]` (metres, z = 0).

A two-sided board (caliscope's: the back face carries a mirror print aligned with the front) is seen mirrored by a
camera behind it: a frame where the board is not found is searched again flipped left-right, and the corners found
are flipped back. Corner i of the back face lies directly behind front corner i: the same point (`corner_<id>`)
without a thickness, `corner_<id>_back` at z = +thickness with one.

Rows of the result: video = the file name without extension, frame = 0-based decoded frame index, point =
`corner_<id>`, x, y in OpenCV pixels (top-left pixel centre is (0, 0)), `source` = "charuco".
"""

from __future__ import annotations

import logging
import os
import tomllib
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dynrecon import video_io
from dynrecon.errors import InputError
from dynrecon.names import VIDEO_SUFFIXES, first_repeated
from tracking.markers import dictionary_id
from tracking.tracks import Tracks

log = logging.getLogger(__name__)

SOURCE_CHARUCO = "charuco"
CM_PER_INCH = 2.54


def corner_name(corner_id: int, *, back: bool = False) -> str:
    return f"corner_{corner_id}_back" if back else f"corner_{corner_id}"


@dataclass(kw_only=True)
class CharucoBoard:
    """A ChArUco board: `columns` x `rows` squares, lengths in metres."""

    columns: int
    rows: int
    square_size: float  # metres
    marker_size: float  # metres
    dictionary: str = "DICT_4X4_50"  # name of an OpenCV predefined aruco dictionary
    inverted: bool = False  # printed inverted: detect on 255 - gray
    legacy_pattern: bool = False  # OpenCV < 4.6 layout (matters for an even number of rows)
    thickness: float = 0.0  # metres between a two-sided board's faces

    @property
    def num_corners(self) -> int:
        return (self.columns - 1) * (self.rows - 1)

    def opencv(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(dictionary_id(self.dictionary, what="aruco"))
        board = cv2.aruco.CharucoBoard((self.columns, self.rows), self.square_size, self.marker_size, dictionary)
        board.setLegacyPattern(self.legacy_pattern)
        return board


# Limits of a real board: a typo beyond them made OpenCV allocate gigabytes or fail inside its constructor.
MAX_SQUARES = 100
MIN_SQUARE_M, MAX_SQUARE_M = 1e-4, 10.0
MIN_ARUCO_SCALE = 0.05
INCH_UNITS = ("inch", "inches", "in")
CM_UNITS = ("cm", "centimeter", "centimeters", "centimetre", "centimetres")


def read_charuco_board(path: str | Path) -> CharucoBoard:
    """caliscope's `charuco.toml` (keys at the top level) or its `config.toml` (a `[charuco]` table); anipose's
    `config.toml` (a `[calibration]` table with `board_type = "charuco"`) or sleap-anipose's `board.toml`
    (`board_x`, `board_y`, `square_length`, ...), their lengths in mm."""
    path = Path(path)
    if path.suffix.lower() in VIDEO_SUFFIXES:  # the board option given a video (one of the videos, out of place)
        raise InputError(
            path,
            "is a video, not a board description",
            fix="--board takes the board's .toml (caliscope's charuco.toml or config.toml, anipose's config.toml)",
        )
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except OSError as error:
        raise InputError(
            path, f"not a readable file ({error.strerror or error})", fix="give the board's .toml"
        ) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise InputError(path, f"not valid TOML: {error}") from None
    if isinstance(data.get("calibration"), dict) and "board_size" in data["calibration"]:
        return _anipose_board(data["calibration"], path, "[calibration]")
    if "board_x" in data:
        return _anipose_board(data, path, None)
    table = data.get("charuco", data)
    where = "[charuco]" if "charuco" in data else None
    if not isinstance(table, dict) or "columns" not in table or "rows" not in table:
        raise InputError(
            path,
            "no ChArUco board (columns, rows) found",
            where=where,
            fix="give caliscope's charuco.toml or config.toml, anipose's config.toml or sleap-anipose's board.toml",
        )
    number = _number_reader(table, path, where)
    columns, rows = number("columns"), number("rows")
    # caliscope spelled the key square_size_overide_cm in its code for a while: accept both.
    override = table.get("square_size_override_cm", table.get("square_size_overide_cm"))
    if override:
        square = (
            number("square_size_override_cm" if "square_size_override_cm" in table else "square_size_overide_cm")
            / 100.0
        )
    else:
        units = str(table.get("units", "inch")).strip().lower()
        if units not in INCH_UNITS + CM_UNITS:
            raise InputError(path, f"units = {units!r} must be inch or cm", where=where)
        per_cm = CM_PER_INCH if units in INCH_UNITS else 1.0
        square = min(number("board_height") / rows, number("board_width") / columns) * per_cm / 100.0
    aruco_scale = number("aruco_scale", 0.75)
    thickness = table.get("thickness_cm", 0.0)
    if isinstance(thickness, bool) or not isinstance(thickness, int | float) or not 0 <= thickness < 100:
        raise InputError(path, f"thickness_cm = {thickness!r} must be a number from 0 to 100", where=where)
    return _checked_board(
        table,
        path,
        where,
        columns=columns,
        rows=rows,
        square=square,
        aruco_scale=aruco_scale,
        dictionary=str(table.get("dictionary", "DICT_4X4_50")),
        thickness=float(thickness) / 100.0,
    )


# sleap-anipose's board.toml key -> anipose's [calibration] key
_ANIPOSE_KEYS = {
    "square_length": "board_square_side_length",
    "marker_length": "board_marker_length",
    "marker_bits": "board_marker_bits",
    "dict_size": "board_marker_dict_number",
}


def _anipose_board(table: dict[str, Any], path: Path, where: str | None) -> CharucoBoard:
    """anipose's `[calibration]` (`board_size = [columns, rows]`, `board_square_side_length`,
    `board_marker_length`, `board_marker_bits`, `board_marker_dict_number`) or sleap-anipose's `board.toml`
    (`board_x`, `board_y`, `square_length`, `marker_length`, `marker_bits`, `dict_size`); lengths in mm, the
    unit anipose's documentation uses. The board is built as aniposelib builds it (OpenCV's current layout)."""
    if where is not None:  # anipose's config.toml: rename its keys to sleap-anipose's
        kind = str(table.get("board_type", "charuco")).strip().lower()
        if kind != "charuco":
            raise InputError(
                path,
                f"board_type = {kind!r}: only a ChArUco board's corners are found and named",
                where=where,
                fix="film a ChArUco board, or track the subject instead",
            )
        size = table["board_size"]
        if not isinstance(size, list) or len(size) != 2:
            raise InputError(path, f"board_size = {size!r} must be [columns, rows]", where=where)
        table = (
            {"board_x": size[0], "board_y": size[1]}
            | {short: table[key] for short, key in _ANIPOSE_KEYS.items() if key in table}
            | {k: v for k, v in table.items() if k in ("inverted", "legacy_pattern")}
        )
    key = {short: (short if where is None else long) for short, long in _ANIPOSE_KEYS.items()}
    if where is not None:
        key |= {"board_x": "board_size[0]", "board_y": "board_size[1]"}
    number = _number_reader(table, path, where, names=key)
    square, marker = number("square_length") / 1000.0, number("marker_length") / 1000.0
    bits, count = number("marker_bits", 4), number("dict_size", 50)
    if bits not in (4, 5, 6, 7) or count not in (50, 100, 250, 1000):
        raise InputError(
            path,
            f"{key['marker_bits']} = {bits:g}, {key['dict_size']} = {count:g}: no such aruco dictionary",
            where=where,
            fix="marker bits 4 to 7 and a dictionary size of 50, 100, 250 or 1000",
        )
    return _checked_board(
        table,
        path,
        where,
        columns=number("board_x"),
        rows=number("board_y"),
        square=square,
        aruco_scale=marker / square,
        dictionary=f"DICT_{int(bits)}X{int(bits)}_{int(count)}",
        thickness=0.0,
    )


def _number_reader(
    table: dict[str, Any], path: Path, where: str | None, *, names: dict[str, str] | None = None
) -> Callable[..., float]:
    """number(key, default): the table's positive number at `key`; errors name the key as the file spells it
    (`names`: key -> the file's name for it)."""

    def number(key: str, default: float | None = None) -> float:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value) or value <= 0:
            shown_key = (names or {}).get(key, key)
            raise InputError(path, f"{shown_key} = {value!r} must be a positive number", where=where)
        return float(value)

    return number


def _checked_board(
    table: dict[str, Any],
    path: Path,
    where: str | None,
    *,
    columns: float,
    rows: float,
    square: float,
    aruco_scale: float,
    dictionary: str,
    thickness: float,
) -> CharucoBoard:
    """The board, after the checks every layout shares: a printable size, a marker inside its square, a
    dictionary with enough markers, and the layout flags (`inverted`, `legacy_pattern`)."""
    if columns != int(columns) or rows != int(rows) or not (2 <= columns <= MAX_SQUARES and 2 <= rows <= MAX_SQUARES):
        raise InputError(
            path, f"columns, rows = {columns:g}, {rows:g} must be integers from 2 to {MAX_SQUARES}", where=where
        )
    if not MIN_SQUARE_M <= square <= MAX_SQUARE_M:
        raise InputError(
            path,
            f"a square of {square:g} m: not a printable board ({MIN_SQUARE_M:g} to {MAX_SQUARE_M:g} m)",
            where=where,
            fix="give the square's edge in cm (square_size_override_cm) or the board's size (board_width, height)",
        )
    if not MIN_ARUCO_SCALE <= aruco_scale < 1:
        raise InputError(
            path,
            f"aruco_scale (marker edge / square edge) = {aruco_scale:g} must be from {MIN_ARUCO_SCALE} to below 1",
            where=where,
        )
    markers = cv2.aruco.getPredefinedDictionary(dictionary_id(dictionary, path, what="aruco")).bytesList.shape[0]
    needed = int(columns) * int(rows) // 2
    if needed > markers:
        raise InputError(
            path,
            f"a {int(columns)} x {int(rows)} board needs {needed} markers; {dictionary} has {markers}",
            where=where,
            fix="give the dictionary the board was printed with",
        )
    flags = {}
    for key in ("inverted", "legacy_pattern"):
        value = table.get(key, False)
        if not isinstance(value, bool):
            raise InputError(path, f"{key} = {value!r} must be true or false", where=where)
        flags[key] = value
    return CharucoBoard(
        columns=int(columns),
        rows=int(rows),
        square_size=square,
        marker_size=square * aruco_scale,
        dictionary=dictionary,
        inverted=flags["inverted"],
        legacy_pattern=flags["legacy_pattern"],
        thickness=thickness,
    )


def _board(board: Path | str | CharucoBoard) -> CharucoBoard:
    return board if isinstance(board, CharucoBoard) else read_charuco_board(board)


def board_corner_positions(board: Path | str | CharucoBoard) -> dict[str, np.ndarray]:
    """`corner_<id>` -> (3,) position on the board in metres (board frame: x along columns, y along rows, z = 0);
    with a thickness also `corner_<id>_back` at z = +thickness (cameras that see the front look along +z)."""
    board = _board(board)
    corners = np.asarray(board.opencv().getChessboardCorners(), dtype=float).reshape(-1, 3)
    positions = {corner_name(i): corner for i, corner in enumerate(corners)}
    if board.thickness > 0:
        positions |= {
            corner_name(i, back=True): corner + np.array([0.0, 0.0, board.thickness])
            for i, corner in enumerate(corners)
        }
    return positions


def detect_corners(
    gray: np.ndarray, detector: cv2.aruco.CharucoDetector, *, inverted: bool = False, mirrored: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Corner ids (K,) int64 and pixel positions (K, 2) of the board in one (H, W) uint8 frame; `mirrored`: the
    board's mirror print (its back face), searched in the frame flipped left-right, positions in the frame's own."""
    image = 255 - gray if inverted else gray
    corners, ids, _, _ = detector.detectBoard(cv2.flip(image, 1) if mirrored else image)
    if ids is None or len(ids) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
    xy = np.asarray(corners, dtype=float).reshape(-1, 2)
    if mirrored:
        xy[:, 0] = gray.shape[1] - 1 - xy[:, 0]  # column c of the flipped frame is column W - 1 - c
    return np.asarray(ids, dtype=np.int64).ravel(), xy


def _detect_video(
    path: Path, board: CharucoBoard, min_corners: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """(frame (N,), corner id (N,), xy (N, 2), back face (N,) bool, decoded frame count) for one video."""
    if not path.is_file():
        raise InputError(path, "video file not found" if not path.exists() else "not a video file")
    capture = video_io.open_video(path)
    detector = cv2.aruco.CharucoDetector(board.opencv())
    frames: list[np.ndarray] = []
    ids: list[np.ndarray] = []
    xy: list[np.ndarray] = []
    back: list[np.ndarray] = []
    index = 0
    last_mirrored = False  # the face seen last is tried first: a camera mostly sees one face
    try:
        while (image := video_io.read(capture)) is not None:
            gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            for mirrored in (last_mirrored, not last_mirrored):
                corner_ids, corner_xy = detect_corners(gray, detector, inverted=board.inverted, mirrored=mirrored)
                if len(corner_ids):
                    last_mirrored = mirrored
                    break
            if len(corner_ids) >= min_corners:
                frames.append(np.full(len(corner_ids), index, dtype=np.int64))
                ids.append(corner_ids)
                xy.append(corner_xy)
                back.append(np.full(len(corner_ids), last_mirrored))
            index += 1
    finally:
        capture.release()
    if index == 0:
        raise InputError(path, "no decodable frames", fix="check the file plays; convert it to H.264")
    if not frames:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, np.zeros((0, 2)), np.zeros(0, dtype=bool), index
    return np.concatenate(frames), np.concatenate(ids), np.concatenate(xy), np.concatenate(back), index


def board_not_found(board: CharucoBoard, path: Path, min_corners: int | None = None) -> InputError:
    """The error for a board found in no frame of any video (`path`: the first one), or in none with `min_corners`
    corners or more: a wrong board file, mostly."""
    enough = f" with {min_corners} or more corners" if min_corners is not None else ""
    return InputError(
        path,
        f"the board ({board.columns} x {board.rows}, {board.dictionary}) was found{enough} in no frame of any video",
        fix="check the board file against the printed board (dictionary, columns and rows, inverted)",
    )


def charuco_tracks(
    videos: Sequence[Path | str],
    board: Path | str | CharucoBoard,
    *,
    min_corners: int = 1,
    workers: int | None = None,
    require_any: bool = True,
) -> Tracks:
    """Board corners in every frame of every video: one row per (video, frame, corner), point `corner_<id>`.

    Frames with fewer than `min_corners` corners are left out; with `require_any`, a board found in no video is an
    error (a wrong board file), else a warning per video. Videos are decoded in `workers` threads
    (default: one per video, at most the CPU count); OpenCV releases the GIL while decoding and detecting.
    """
    board = _board(board)
    paths = [Path(v) for v in videos]
    names = [p.stem for p in paths]
    twice = first_repeated(names)
    if twice is not None:
        raise InputError(paths[twice], f"two videos are named {names[twice]!r}", fix="video names must be unique")
    workers = workers or max(1, min(len(paths), os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        results = list(pool.map(lambda p: _detect_video(p, board, min_corners), paths))
    video: list[str] = []
    for name, path, (frame, _, _, back, count) in zip(names, paths, results, strict=True):
        video += [name] * len(frame)
        log.info("%s: board corners in %d of %d frames (%d corners)", path, len(np.unique(frame)), count, len(frame))
        if back.any():
            log.info(
                "%s: the board's back face (its mirror print) in %d of those frames", path, len(np.unique(frame[back]))
            )
        if not len(frame):
            log.warning("%s: the board was found in none of its %d frames", path, count)
    if require_any and results and not any(len(r[0]) for r in results):
        raise board_not_found(board, paths[0], min_corners if min_corners > 1 else None)
    frame = np.concatenate([r[0] for r in results]) if results else np.zeros(0, dtype=np.int64)
    ids = np.concatenate([r[1] for r in results]) if results else np.zeros(0, dtype=np.int64)
    xy = np.concatenate([r[2] for r in results]) if results else np.zeros((0, 2))
    back = np.concatenate([r[3] for r in results]) if results else np.zeros(0, dtype=bool)
    back &= board.thickness > 0  # without a thickness the faces' corners are the same points
    return Tracks(
        video=video,
        frame=frame,
        point=[corner_name(int(i), back=bool(b)) for i, b in zip(ids, back, strict=True)],
        xy=xy,
        extra={"source": [SOURCE_CHARUCO] * len(video)},
    )
