"""Camera registration: a pose and intrinsics for every frame of every video, in one world frame.

Owns the `cameras.json` contract (`sfm.cameras`). The public front:

    import sfm

    path = sfm.register(["a.mp4", "b.mp4"], "WS", sfm.RegisterOptions(max_frames=60))  # WS/cameras.json
    path = sfm.import_calibration("Calib.qca.txt", ["a.mp4", "b.mp4"], "WS")  # static calibrated cameras
    cameras = sfm.read_cameras(path)

Names are loaded on first use: `import sfm` (and `sfm.cameras`, which the solver reads) stays cheap, and
pycolmap or OpenCV load only when a stage runs. Everything else in the package is internal.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dynrecon.lazy import lazy_exports

if TYPE_CHECKING:
    from sfm.calibration import run as import_calibration
    from sfm.cameras import CameraSet, FrameCamera, VideoCameras, read_cameras, write_cameras
    from sfm.options import (
        CalibrationFormat,
        CameraMotion,
        ImportCalibrationOptions,
        Localize,
        Mapper,
        RegisterOptions,
        SubjectPath,
        Units,
    )
    from sfm.stage import RegistrationError
    from sfm.stage import run as register

# public name -> (module, attribute)
_FRONT = {
    "register": ("sfm.stage", "run"),
    "RegistrationError": ("sfm.stage", "RegistrationError"),
    "RegisterOptions": ("sfm.options", "RegisterOptions"),
    "CameraMotion": ("sfm.options", "CameraMotion"),
    "Localize": ("sfm.options", "Localize"),
    "Mapper": ("sfm.options", "Mapper"),
    "SubjectPath": ("sfm.options", "SubjectPath"),
    "import_calibration": ("sfm.calibration", "run"),
    "ImportCalibrationOptions": ("sfm.options", "ImportCalibrationOptions"),
    "CalibrationFormat": ("sfm.options", "CalibrationFormat"),
    "Units": ("sfm.options", "Units"),
    "CameraSet": ("sfm.cameras", "CameraSet"),
    "VideoCameras": ("sfm.cameras", "VideoCameras"),
    "FrameCamera": ("sfm.cameras", "FrameCamera"),
    "read_cameras": ("sfm.cameras", "read_cameras"),
    "write_cameras": ("sfm.cameras", "write_cameras"),
}

__all__ = [
    "CalibrationFormat",
    "CameraMotion",
    "CameraSet",
    "FrameCamera",
    "ImportCalibrationOptions",
    "Localize",
    "Mapper",
    "RegisterOptions",
    "RegistrationError",
    "SubjectPath",
    "Units",
    "VideoCameras",
    "import_calibration",
    "read_cameras",
    "register",
    "write_cameras",
]


__getattr__, __dir__ = lazy_exports(__name__, _FRONT)
