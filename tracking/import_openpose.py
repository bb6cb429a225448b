"""OpenPose JSON, one file per frame (`--write_json`): `people[k].pose_keypoints_2d` = [x0, y0, c0, x1, ...].

Files are named `<video>_<12-digit frame>_keypoints.json`; the frame is the last number in the name (files
without one are numbered in name order). A keypoint with confidence 0 is a missing detection. Names follow
BODY_25 (25 triplets) or COCO (18 triplets); other counts are named `kp0`, `kp1`, ...
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from dynrecon.errors import InputError
from dynrecon.readers import parse_frame
from tracking.detections import Detection

BODY_25 = (
    "Nose",
    "Neck",
    "RShoulder",
    "RElbow",
    "RWrist",
    "LShoulder",
    "LElbow",
    "LWrist",
    "MidHip",
    "RHip",
    "RKnee",
    "RAnkle",
    "LHip",
    "LKnee",
    "LAnkle",
    "REye",
    "LEye",
    "REar",
    "LEar",
    "LBigToe",
    "LSmallToe",
    "LHeel",
    "RBigToe",
    "RSmallToe",
    "RHeel",
)
COCO_18 = (
    "Nose",
    "Neck",
    "RShoulder",
    "RElbow",
    "RWrist",
    "LShoulder",
    "LElbow",
    "LWrist",
    "RHip",
    "RKnee",
    "RAnkle",
    "LHip",
    "LKnee",
    "LAnkle",
    "REye",
    "LEye",
    "REar",
    "LEar",
)
_FRAME = re.compile(r"(\d+)(?!.*\d)")


def keypoint_names(count: int) -> tuple[str, ...]:
    if count == len(BODY_25):
        return BODY_25
    if count == len(COCO_18):
        return COCO_18
    return tuple(f"kp{i}" for i in range(count))


def openpose_files(path: Path) -> list[Path]:
    """The JSON files of a folder (sorted by name), or the one file given."""
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".json")
        if not files:
            raise InputError(path, "no .json files in this folder", fix="give OpenPose's --write_json folder")
        return files
    if not path.is_file():
        raise InputError(path, "file or folder not found")
    return [path]


def video_name_from_openpose(path: Path) -> str:
    """`out/cam01_000000000012_keypoints.json` or the folder `out/cam01_json` -> `cam01`."""
    name = path.stem if path.is_file() else path.name
    name = re.sub(r"_?\d*_keypoints$", "", name)
    name = re.sub(r"_json$", "", name)
    return name or path.stem


def read_openpose(path: Path, video: str, person: int = 0) -> list[Detection]:
    files = openpose_files(path)
    detections: list[Detection] = []
    seen: dict[int, Path] = {}
    layout: tuple[int, Path] | None = None  # the keypoint count of the first file with a person, and that file
    for order, file in enumerate(files):
        match = _FRAME.search(file.stem)
        frame = parse_frame(match.group(1), file, "file name") if match else order
        if frame in seen:
            raise InputError(
                file, f"frame {frame} again (also {seen[frame].name})", fix="one JSON file per frame, numbered by frame"
            )
        seen[frame] = file
        try:
            data = json.loads(file.read_text(encoding="utf-8"))
        except OSError as error:
            raise InputError(file, f"cannot read: {error.strerror or error}") from None
        except (ValueError, UnicodeDecodeError, RecursionError) as error:  # ValueError: also >4300-digit ints
            raise InputError(file, f"not valid JSON: {str(error)[:200]}") from None
        people = data.get("people") if isinstance(data, dict) else None
        if not isinstance(people, list):
            raise InputError(file, "no 'people' list", fix="expected OpenPose --write_json output")
        if person >= len(people):
            continue  # nobody detected in this frame
        flat = people[person].get("pose_keypoints_2d") if isinstance(people[person], dict) else None
        if not isinstance(flat, list) or len(flat) % 3 or not all(isinstance(v, int | float) for v in flat):
            raise InputError(file, f"people[{person}].pose_keypoints_2d is not a list of x, y, c triplets")
        if layout is None:
            layout = (len(flat) // 3, file)
        elif len(flat) // 3 != layout[0]:  # BODY_25 and COCO_18 name the same index differently
            raise InputError(
                file,
                f"{len(flat) // 3} keypoints where {layout[1].name} has {layout[0]}: two OpenPose models in one folder",
                fix="import each model's output separately (and map the names with --map)",
            )
        names = keypoint_names(len(flat) // 3)
        for k, name in enumerate(names):
            x, y, c = (float(v) for v in flat[3 * k : 3 * k + 3])
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(c)):
                raise InputError(
                    file,
                    f"people[{person}] keypoint {k} ({name}) is x, y, c = {x:g}, {y:g}, {c:g}: not finite",
                    fix="OpenPose writes finite numbers (0, 0, 0 where it found nothing); re-export the JSON",
                )
            if c <= 0.0:
                continue
            detections.append(Detection(video=video, frame=frame, point=name, x=x, y=y, score=c, where=file.name))
    return detections
