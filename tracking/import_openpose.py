"""OpenPose JSON, one file per frame (`--write_json`): `people[k].pose_keypoints_2d` = [x0, y0, c0, x1, ...].

Files are named `<video>_<12-digit frame>_keypoints.json`; the frame is the last number in the name (files
without one are numbered in name order). A keypoint with confidence 0 is a missing detection. Names follow
BODY_25 or BODY_25B (25 triplets each, told apart by which keypoints lie together in the head) or COCO (18
triplets); other counts are named `kp0`, `kp1`, ... With several people in a frame, people are linked through the
frames (tracking/people.py) and one person, or each, is imported.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np

from dynrecon.errors import InputError
from dynrecon.readers import parse_frame
from tracking.detections import Detection
from tracking.people import link_people, person_point

log = logging.getLogger(__name__)

# keypoints 19-24 of both 25-keypoint models, in the same order
FEET = ("LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel")
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
    *FEET,
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
# OpenPose's experimental 25-keypoint model (Pose2Sim's default): as many triplets as BODY_25, other names
BODY_25B = (
    "Nose",
    "LEye",
    "REye",
    "LEar",
    "REar",
    "LShoulder",
    "RShoulder",
    "LElbow",
    "RElbow",
    "LWrist",
    "RWrist",
    "LHip",
    "RHip",
    "LKnee",
    "RKnee",
    "LAnkle",
    "RAnkle",
    "Neck",
    "Head",
    *FEET,
)
# Keypoints 0-4 are BODY_25B's head (nose, eyes, ears) and BODY_25's nose, neck and right arm; 15-18 are BODY_25's
# eyes and ears and BODY_25B's ankles, neck and head: the spread of the first set over the second's, median over the
# poses, is under this for BODY_25B and over its inverse for BODY_25 (docs/formats.md).
HEAD_RATIO = 0.5
_FRAME = re.compile(r"(\d+)(?!.*\d)")


def keypoint_names(count: int, poses: list[np.ndarray] | None = None, source: Path | None = None) -> tuple[str, ...]:
    """The names of `count` keypoints; 25 are BODY_25's or BODY_25B's, whichever `poses` ((count, 3) x, y,
    confidence) fit (`_head_ratio`); BODY_25 where they cannot tell, with a warning naming `source`."""
    if count == len(BODY_25):
        ratio = _head_ratio(poses or [])
        if ratio <= HEAD_RATIO:
            log.info("%s: BODY_25B keypoints (eyes and ears at 1-4)", source)
            return BODY_25B
        if ratio < 1 / HEAD_RATIO:
            log.warning(
                "%s: 25 keypoints: BODY_25 or BODY_25B (Pose2Sim's default), which name them differently, cannot be "
                "told apart from the poses; named as BODY_25: rename the points with --map if the model was BODY_25B",
                source,
            )
        return BODY_25
    if count == len(COCO_18):
        return COCO_18
    return tuple(f"kp{i}" for i in range(count))


def _head_ratio(poses: list[np.ndarray]) -> float:
    """Median over `poses` of the mean distance between the seen keypoints of 0-4 over that between the seen
    keypoints of 15-18 (two or more of each: a person seen from behind shows ears, not eyes): under 1 for BODY_25B,
    over 1 for BODY_25; 1 without such a pose."""
    ratios = []
    for pose in poses:
        first, second = (_spread(pose, keypoints) for keypoints in ((0, 1, 2, 3, 4), (15, 16, 17, 18)))
        if first is not None and second:
            ratios.append(first / second)
    return float(np.median(ratios)) if ratios else 1.0


def _spread(pose: np.ndarray, keypoints: tuple[int, ...]) -> float | None:
    """The mean distance between the seen ones of `keypoints` of `pose`; None with fewer than two seen."""
    seen = pose[[k for k in keypoints if pose[k, 2] > 0], :2]
    if len(seen) < 2:
        return None
    gaps = np.linalg.norm(seen[:, None] - seen[None], axis=-1)
    return float(gaps.sum() / (len(seen) * (len(seen) - 1)))


def openpose_files(path: Path) -> list[Path]:
    """The JSON files of a folder (sorted by name) that follow its main naming pattern, or the one file given."""
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".json")
        if not files:
            raise InputError(path, "no .json files in this folder", fix="give OpenPose's --write_json folder")
        return _main_pattern(path, files)
    if not path.is_file():
        raise InputError(path, "file or folder not found")
    return [path]


def _main_pattern(folder: Path, files: list[Path]) -> list[Path]:
    """The files named like most of them (`cam03.0012.json` beside a stray `del_000000_0.json`: Pose2Sim's demo);
    the others are left out with a warning. Patterns as common as the main one are kept: frames numbered twice
    are then refused by name."""
    groups: dict[str, list[Path]] = {}
    for file in files:
        groups.setdefault(_FRAME.sub("#", file.stem), []).append(file)
    if len(groups) == 1:
        return files
    ranked = sorted(groups.values(), key=len, reverse=True)
    if len(ranked[0]) == len(ranked[1]):
        return files
    others = [f.name for group in ranked[1:] for f in group]
    log.warning(
        "%s: %d of its %d JSON files are named unlike the others and left out (%s%s)",
        folder,
        len(others),
        len(files),
        ", ".join(others[:4]),
        ", ..." if len(others) > 4 else "",
    )
    return ranked[0]


def video_name_from_openpose(path: Path) -> str:
    """`out/cam01_000000000012_keypoints.json` or the folder `out/cam01_json` -> `cam01`."""
    name = path.stem if path.is_file() else path.name
    name = re.sub(r"_?\d*_keypoints$", "", name)
    name = re.sub(r"_json$", "", name)
    return name or path.stem


def read_openpose(path: Path, video: str, person: int = 0, every_person: bool = False) -> list[Detection]:
    """The detections of one person (`person`: 0 = the one seen most, 1 = the next, ...; people are linked
    through the frames by tracking/people.py, not taken by their index in `people[]`), or of every person
    (`every_person`: points named `person<N>_<keypoint>`, as DeepLabCut names its individuals)."""
    frames = _read_frames(openpose_files(path))
    identities, people = link_people([(frame, poses) for frame, _, poses in frames])
    if len(people) > 1:
        log.warning(
            "%s: %d people linked through the frames (%s)%s; --person N imports another, --person all every one",
            path.name,
            len(people),
            ", ".join(f"person {n}: {p.keypoints} keypoints in {p.frames} frames" for n, p in enumerate(people)),
            "" if every_person else f": person {person} imported",
        )
    if not every_person and people and person >= len(people):
        raise InputError(
            path,
            f"--person {person}: only {len(people)} people were linked through the frames",
            fix=f"give --person 0 to {len(people) - 1} (0 is the person seen most) or --person all",
        )
    every = [pose for _, _, poses in frames for pose in poses]
    names = keypoint_names(len(every[0]), every, path) if every else ()
    detections: list[Detection] = []
    for (frame, file, poses), ids in zip(frames, identities, strict=True):
        for pose, identity in zip(poses, ids, strict=True):
            if not every_person and identity != person:
                continue
            for k, name in enumerate(names):
                x, y, c = (float(v) for v in pose[k])
                if c > 0.0:
                    point = person_point(identity, name) if every_person else name
                    detections.append(
                        Detection(video=video, frame=frame, point=point, x=x, y=y, score=c, where=file.name)
                    )
    return detections


def _read_frames(files: list[Path]) -> list[tuple[int, Path, list[np.ndarray]]]:
    """Per file, in frame order: (frame, file, [(K, 3) x, y, confidence of each person with a pose])."""
    frames: list[tuple[int, Path, list[np.ndarray]]] = []
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
        poses = []
        for index, entry in enumerate(people):
            flat = entry.get("pose_keypoints_2d") if isinstance(entry, dict) else None
            if not isinstance(flat, list) or len(flat) % 3 or not all(isinstance(v, int | float) for v in flat):
                raise InputError(file, f"people[{index}].pose_keypoints_2d is not a list of x, y, c triplets")
            if not flat:
                continue  # a face or hands without a body
            if layout is None:
                layout = (len(flat) // 3, file)
            elif len(flat) // 3 != layout[0]:  # BODY_25 and COCO_18 name the same index differently
                raise InputError(
                    file,
                    f"{len(flat) // 3} keypoints where {layout[1].name} has {layout[0]}: two OpenPose models in one "
                    "folder",
                    fix="import each model's output separately (and map the names with --map)",
                )
            pose = np.array(flat, dtype=float).reshape(-1, 3)
            bad = np.flatnonzero(~np.isfinite(pose).all(axis=1))
            if bad.size:
                k = int(bad[0])
                x, y, c = pose[k]
                raise InputError(
                    file,
                    f"people[{index}] keypoint {k} is x, y, c = {x:g}, {y:g}, {c:g}: not finite",
                    fix="OpenPose writes finite numbers (0, 0, 0 where it found nothing); re-export the JSON",
                )
            pose[pose[:, 2] <= 0.0, 2] = 0.0
            if pose[:, 2].any():
                poses.append(pose)
        frames.append((frame, file, poses))
    frames.sort(key=lambda item: item[0])
    return frames
