"""The formats phones write (issue 19) and damaged videos (issue 18), on tiny files this module makes with ffmpeg.

Every file is probed and decoded by dynrecon's readers and checked against ffmpeg's own decoding (`ffmpeg -f rawvideo`)
and ffprobe's frame timestamps. The rotated video is checked in every reader (probe, SfM frames, tracking, the
labeling page) against the same video stored upright.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from dynrecon.errors import InputError
from labeling.frames import FrameCache
from labeling.frames import probe_video as labeling_probe
from sfm.export import opencv_intrinsics
from sfm.frames import Resize, image_name, write_frames
from sfm.plan import VideoPlan
from sfm.report import _video_entry
from sfm.video import ProbedVideo, probe_video, read_frames
from tracking.frames import VideoFrames

FFMPEG = shutil.which("ffmpeg")
FFPROBE = shutil.which("ffprobe")
pytestmark = pytest.mark.skipif(
    FFMPEG is None or FFPROBE is None,
    reason="ffmpeg/ffprobe not installed (.ci/run installs Debian's ffmpeg): the test videos are made with it",
)

WIDTH, HEIGHT, FPS = 160, 96, 30
SOURCE = ["-f", "lavfi", "-i", f"testsrc2=size={WIDTH}x{HEIGHT}:rate={FPS}:duration=1"]
LONG_SOURCE = ["-f", "lavfi", "-i", f"testsrc2=size={WIDTH}x{HEIGHT}:rate={FPS}:duration=2"]
# One encoder thread: the same bitstream on every machine, so the damaged files lose the same frames.
X264 = ["-c:v", "libx264", "-pix_fmt", "yuv420p", "-threads", "1"]
X265 = ["-c:v", "libx265", "-x265-params", "log-level=error:pools=none", "-tag:v", "hvc1", "-pix_fmt", "yuv420p"]
LOSSLESS = ["-c:v", "libx264", "-qp", "0", "-pix_fmt", "yuv420p", "-threads", "1"]
# Irregular frame times in milliseconds (a phone dropping to a lower rate and back, with jitter), kept by
# -fps_mode vfr and a millisecond encoder time base.
VFR_FILTER = r"settb=1/1000,setpts='N*33+if(gte(N\,12)\,(N-12)*40\,0)+if(gte(N\,20)\,-(N-20)*40\,0)+mod(N\,3)*5'"


def _ffmpeg(*args: str | Path) -> None:
    assert FFMPEG is not None
    subprocess.run([FFMPEG, "-hide_banner", "-loglevel", "error", "-y", *map(str, args)], check=True)


def _has_x265() -> bool:
    assert FFMPEG is not None
    encoders = subprocess.run([FFMPEG, "-hide_banner", "-encoders"], capture_output=True, text=True, check=True)
    return "libx265" in encoders.stdout


def _damage(source: Path, target: Path, *, keep: float | None = None, zero: tuple[float, float] | None = None) -> Path:
    data = bytearray(source.read_bytes())
    if zero is not None:
        start, length = int(len(data) * zero[0]), int(len(data) * zero[1])
        data[start : start + length] = bytes(length)
    if keep is not None:
        data = data[: int(len(data) * keep)]
    target.write_bytes(bytes(data))
    return target


@pytest.fixture(scope="module")
def videos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Every test video, made once: name -> path."""
    folder = tmp_path_factory.mktemp("phone_formats")
    made = {}
    for name, codec in [("h264.mp4", X264), ("h264.mov", X264), ("hevc.mp4", X265), ("hevc.mov", X265)]:
        if codec is X265 and not _has_x265():
            continue
        made[name] = folder / name
        _ffmpeg(*SOURCE, *codec, made[name])
    # Portrait content, stored upright, and stored landscape (turned clockwise) with a 90° display rotation.
    made["upright"] = folder / "upright.mp4"
    _ffmpeg("-f", "lavfi", "-i", f"testsrc2=size={HEIGHT}x{WIDTH}:rate={FPS}:duration=1", *LOSSLESS, made["upright"])
    stored = folder / "stored_landscape.mp4"
    _ffmpeg("-i", made["upright"], "-vf", "transpose=1", *LOSSLESS, stored)
    made["rotated"] = folder / "rotated.mp4"
    _ffmpeg("-i", stored, "-c", "copy", "-metadata:s:v:0", "rotate=90", made["rotated"])
    made["vfr.mp4"] = folder / "vfr.mp4"
    _ffmpeg(*SOURCE, "-vf", VFR_FILTER, "-fps_mode", "vfr", "-enc_time_base", "1/1000", *X264, made["vfr.mp4"])
    made["4k"] = folder / "4k.mp4"
    _ffmpeg(
        "-f",
        "lavfi",
        "-i",
        "testsrc2=size=3840x2160:rate=30",
        "-frames:v",
        "3",
        *X264,
        "-preset",
        "ultrafast",
        made["4k"],
    )
    # Audio beside the video; the index (moov) first, as a phone's finished file has it somewhere readable.
    made["audio"] = folder / "audio.mp4"
    sine = ["-f", "lavfi", "-i", "sine=frequency=440:duration=2"]
    _ffmpeg(
        *LONG_SOURCE, *sine, *X264, "-g", "10", "-c:a", "aac", "-shortest", "-movflags", "+faststart", made["audio"]
    )
    made["cut_tail"] = _damage(made["audio"], folder / "cut_tail.mp4", keep=0.6)
    # Sound that runs on after the picture, in a container without a frame index (the count is duration x rate).
    made["long_sound"] = folder / "long_sound.mkv"
    _ffmpeg(*SOURCE, "-f", "lavfi", "-i", "sine=frequency=440:duration=3", *X264, "-c:a", "aac", made["long_sound"])
    no_index = folder / "index_last.mp4"
    _ffmpeg(*LONG_SOURCE, *X264, "-g", "10", no_index)
    made["cut_no_index"] = _damage(no_index, folder / "cut_no_index.mp4", keep=0.6)
    made["zeroed_middle"] = _damage(no_index, folder / "zeroed_middle.mp4", zero=(1 / 3, 0.1))
    return made


def _reference(path: Path, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """(F, height, width, 3) BGR frames as ffmpeg itself decodes them (rotation applied, like a player)."""
    assert FFMPEG is not None
    raw = subprocess.run(
        [
            FFMPEG,
            "-v",
            "quiet",
            "-i",
            str(path),
            "-fps_mode",
            "passthrough",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "bgr24",
            "-",
        ],
        capture_output=True,
    ).stdout
    return np.frombuffer(raw, np.uint8).reshape(-1, height, width, 3)


def _pts(path: Path) -> np.ndarray:
    """ffprobe's presentation time of every video frame, seconds."""
    assert FFPROBE is not None
    out = subprocess.run(
        [FFPROBE, "-v", "error", "-select_streams", "v:0", "-show_entries", "frame=pts_time", "-of", "csv=p=0",
         str(path)],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    return np.array([float(line.strip(",")) for line in out.split() if line.strip(",")])


def _image(path: Path | None = None, data: bytes | None = None) -> np.ndarray:
    """A JPEG from a file or from bytes, as BGR."""
    image = cv2.imread(str(path)) if path is not None else cv2.imdecode(np.frombuffer(data or b"", np.uint8), 1)
    assert image is not None, path
    return image


def _decoded(path: Path, count: int) -> np.ndarray:
    return np.array([image for _, image in read_frames(path, np.arange(count))])


@pytest.mark.parametrize("name", ["h264.mp4", "h264.mov", "hevc.mp4", "hevc.mov"])
def test_phone_codecs_probe_and_decode_like_ffmpeg(videos: dict[str, Path], name: str) -> None:
    if name not in videos:
        pytest.skip("this ffmpeg has no libx265 encoder to make the HEVC file")
    info = probe_video(videos[name])
    assert (info.width, info.height, info.num_frames, info.expected_frames) == (WIDTH, HEIGHT, FPS, FPS)
    assert info.fps == pytest.approx(FPS) and info.missing is None and info.rotation == 0
    pts = _pts(videos[name])
    assert np.abs(info.times - (pts - pts[0])).max() < 1e-3
    reference = _reference(videos[name])
    assert np.abs(_decoded(videos[name], FPS).astype(int) - reference).max() <= 1


def _readers(path: Path, tmp: Path) -> dict[str, np.ndarray]:
    """Frame 5 of `path` as each reader returns it (BGR, or gray for tracking), and the sizes they report."""
    info = probe_video(path)
    resize = Resize.for_video(info, 1280)
    write_frames(info, np.array([5]), tmp, resize)
    labeling = labeling_probe(info.name, path)
    cache = FrameCache({info.name: labeling})
    page = _image(data=cache.jpeg(info.name, 5))
    cache.close()
    tracking = VideoFrames(path)
    gray = tracking.gray(5)
    tracking.close()
    return {
        "sizes": np.array([info.width, info.height, resize.width, resize.height, labeling.width, labeling.height]),
        "sfm": dict(read_frames(path, np.array([5])))[5],
        "sfm_jpeg": _image(tmp / image_name(info.name, 5)),
        "tracking": gray,
        "labeling": page,
    }


def test_rotated_portrait_video_is_upright_and_identical_in_every_reader(
    videos: dict[str, Path], tmp_path: Path
) -> None:
    assert probe_video(videos["rotated"]).rotation in (90, 270)
    assert probe_video(videos["upright"]).rotation == 0
    upright = _readers(videos["upright"], tmp_path / "upright")
    rotated = _readers(videos["rotated"], tmp_path / "rotated")
    np.testing.assert_array_equal(upright["sizes"], [HEIGHT, WIDTH] * 3)
    np.testing.assert_array_equal(rotated["sizes"], upright["sizes"])
    for reader in ("sfm", "tracking"):
        np.testing.assert_array_equal(rotated[reader], upright[reader], err_msg=reader)
    for reader in ("sfm_jpeg", "labeling"):  # JPEG: same shape, same picture up to compression
        assert rotated[reader].shape == upright[reader].shape == (WIDTH, HEIGHT, 3), reader
        assert np.abs(rotated[reader].astype(int) - upright[reader]).mean() < 1.0, reader
    assert (
        np.abs(upright["sfm"].astype(int) - _reference(videos["rotated"], HEIGHT, WIDTH)[5]).max() <= 1
    )  # as ffmpeg shows it


def test_tracks_of_a_rotated_video_are_said_to_be_upright_pixels(
    videos: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Labels or tracks of a phone video with a rotation flag, from a tool that ignores it, would be in the stored
    frame's pixels: register and run say once per such video that the pixels are read as upright ones."""
    import logging

    from dynrecon.pipeline import PipelineOptions, _check
    from sfm.options import RegisterOptions
    from sfm.stage import check_inputs
    from tracking.tracks import Tracks, write_tracks

    tracks = Tracks.from_rows([("rotated", 0, "p", 10.0, 20.0), ("upright", 0, "p", 10.0, 20.0)])
    path = write_tracks(tmp_path / "tracks.csv", tracks)
    caplog.set_level(logging.WARNING)
    infos = [probe_video(videos["rotated"]), probe_video(videos["upright"])]
    check_inputs(RegisterOptions(), infos, tracks)
    _check([videos["rotated"], videos["upright"]], PipelineOptions(tracks=path))
    said = [r.getMessage() for r in caplog.records if "rotation flag" in r.getMessage()]
    assert len(said) == 2 and all(m.startswith("rotated: the video carries a rotation flag of") for m in said)
    assert f"the pixels in {path} must be those of the upright frames" in said[1]


def test_variable_frame_rate_times_are_the_container_timestamps(videos: dict[str, Path]) -> None:
    info = probe_video(videos["vfr.mp4"])
    pts = _pts(videos["vfr.mp4"])
    assert info.num_frames == len(pts) == FPS
    assert np.ptp(np.diff(pts)) > 0.05  # the intervals really vary
    assert np.abs(pts * FPS - np.round(pts * FPS)).max() > 0.1  # times off the 30 fps grid
    assert np.abs(info.times - (pts - pts[0])).max() < 1e-3
    assert info.variable_frame_rate and info.fps is None


def test_4k_decodes_and_is_downscaled_for_features_with_intrinsics_in_full_pixels(
    videos: dict[str, Path], tmp_path: Path
) -> None:
    info = probe_video(videos["4k"])
    assert (info.width, info.height, info.num_frames) == (3840, 2160, 3)
    resize = Resize.for_video(info, 1280)
    write_frames(info, np.arange(3), tmp_path, resize)
    assert _image(tmp_path / image_name(info.name, 2)).shape == (720, 1280, 3)
    # A camera found on the 1280 px frames, brought back to the 3840 px video: the same rays, full-size pixels.
    small = pycolmap.Camera(model="SIMPLE_PINHOLE", width=1280, height=720, params=[1000.0, 640.0, 360.0])
    K, _ = opencv_intrinsics(small, resize)
    np.testing.assert_allclose(K, np.array([[3000.0, 0, 1919.5], [0, 3000.0, 1079.5], [0, 0, 1]]))
    rays = np.array([[0.1, -0.2, 1.0], [-0.3, 0.25, 1.0]])
    full = (rays @ K.T)[:, :2]
    np.testing.assert_allclose(resize.to_small(full) + 0.5, small.img_from_cam(rays), atol=1e-9)  # COLMAP's +0.5


def test_audio_track_is_ignored(videos: dict[str, Path]) -> None:
    info = probe_video(videos["audio"])
    assert (info.num_frames, info.expected_frames, info.missing) == (2 * FPS, 2 * FPS, None)
    assert np.abs(_decoded(videos["audio"], 2 * FPS).astype(int) - _reference(videos["audio"])).max() <= 1


def test_sound_longer_than_the_picture_is_not_called_damage(
    videos: dict[str, Path], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    info = probe_video(videos["long_sound"])
    assert info.num_frames == FPS and info.expected_frames is not None and info.expected_frames > FPS
    message = _one_warning(caplog, videos["long_sound"])
    assert "sound runs on after the picture" in message and "damaged" not in message
    assert np.abs(_decoded(videos["long_sound"], FPS).astype(int) - _reference(videos["long_sound"])).max() <= 1


def _one_warning(caplog: pytest.LogCaptureFixture, path: Path) -> str:
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and str(path) in r.getMessage()]
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    return warnings[0]


def _report_entry(info: ProbedVideo) -> dict[str, object]:
    resize = Resize.for_video(info, 1280)
    return _video_entry(VideoPlan(info=info, resize=resize, sfm_frames=np.arange(2), wanted=np.arange(2)), {})


def test_corrupt_tail_keeps_the_frames_before_it_and_says_so(
    videos: dict[str, Path], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    path = videos["cut_tail"]
    info = probe_video(path)
    assert info.expected_frames == 2 * FPS and 0 < info.num_frames < 2 * FPS
    message = _one_warning(caplog, path)
    assert message == info.missing and f"of {2 * FPS} frames decoded" in message and "after frame" in message
    # Up to the first lost frame, the frames are the intact file's, under the same numbers.
    gaps = np.flatnonzero(np.diff(info.times) > 1.5 / FPS)
    intact = int(gaps[0]) + 1 if len(gaps) else info.num_frames
    assert intact >= 0.9 * info.num_frames
    np.testing.assert_array_equal(_decoded(path, intact), _decoded(videos["audio"], intact))
    caplog.clear()
    assert len(VideoFrames(path)) == info.num_frames
    assert info.missing in _one_warning(caplog, path)  # `track` says it too: later frame numbers are shifted
    entry = _report_entry(info)
    assert entry["frames_missing"] == message and entry["frames_expected"] == 2 * FPS


def test_recording_cut_off_before_its_index_is_a_one_line_error(videos: dict[str, Path]) -> None:
    with pytest.raises(InputError, match="cannot open this video") as error:
        probe_video(videos["cut_no_index"])
    assert str(videos["cut_no_index"]) in str(error.value) and "\n" not in str(error.value)


def test_zeroed_middle_is_detected_located_and_skipped(
    videos: dict[str, Path], caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 18: bytes zeroed in the middle used to end the video there, silently."""
    caplog.set_level(logging.WARNING)
    path = videos["zeroed_middle"]
    info = probe_video(path)
    message = _one_warning(caplog, path)
    assert info.expected_frames == 2 * FPS and info.num_frames < 2 * FPS and message == info.missing
    assert "between frames" in message
    assert info.times[-1] > 1.9  # decoding went on after the damage, to the end of the video
    # ffmpeg skips the same frames; from the next keyframe on, the pictures are the same as ffmpeg's.
    pts = _pts(path)
    np.testing.assert_allclose(info.times, pts - pts[0], atol=1e-3)
    decoded = _decoded(path, info.num_frames)
    same = np.abs(decoded.astype(int) - _reference(path)).max(axis=(1, 2, 3)) <= 1
    assert same[:10].all() and same[-10:].all(), np.flatnonzero(~same)
    # Every reader numbers the frames after the gap the same way.
    tracking = VideoFrames(path)
    assert len(tracking) == info.num_frames
    for index in (0, info.num_frames // 2, info.num_frames - 1):
        np.testing.assert_array_equal(tracking.gray(index), cv2.cvtColor(decoded[index], cv2.COLOR_BGR2GRAY))
    cache = FrameCache({info.name: labeling_probe(info.name, path)})
    assert cache.wait_scanned(30) and cache.frame_count(info.name) == info.num_frames
    cache.close()
    assert _report_entry(info)["frames_missing"] == message
