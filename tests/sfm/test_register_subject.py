"""`pose_from_subject` (sfm/register_subject.py): how the subject path joins the background's cameras."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sfm.frames import Resize
from sfm.options import RegisterOptions
from sfm.plan import FramePose, VideoPlan
from sfm.register_subject import pose_from_subject
from sfm.subject import SubjectCamera, SubjectResult
from sfm.subject.stability import Stability
from sfm.video import ProbedVideo
from tracking.tracks import Tracks


def _plan(folder: Path, name: str, static: bool) -> VideoPlan:
    return VideoPlan(
        info=ProbedVideo(
            path=folder / f"{name}.mp4", name=name, width=640, height=480, times=np.arange(30) / 30.0, nominal_fps=30.0
        ),
        resize=Resize(scale=1.0, width=640, height=480),
        sfm_frames=np.zeros(0, dtype=np.int64),
        wanted=np.arange(30),
        static=static,
    )


def _tracks(videos: list[str]) -> Tracks:
    rng = np.random.default_rng(0)
    rows = [(v, f, p) for v in videos for f in range(30) for p in ("a", "b", "c")]
    return Tracks(
        video=[r[0] for r in rows],
        frame=np.array([r[1] for r in rows]),
        point=[r[2] for r in rows],
        xy=rng.uniform(100, 400, (len(rows), 2)),
    )


def _cameras_apart(names: list[str]) -> list[SubjectCamera]:
    """A stand-in subject path's cameras, one metre apart along the diagonal."""
    return [
        SubjectCamera(
            name=n, K=np.eye(3), dist=None, R=np.eye(3), t=np.full(3, float(i)), offset=0.0, inliers=50, residual_px=1
        )
        for i, n in enumerate(names)
    ]


def test_one_anchor_among_other_background_cameras_is_refused(tmp_path: Path) -> None:
    """One background-posed static video fixes the subject path's frame but not its scale, and the handheld video
    the background posed has no tracks: the subject path's cameras would sit at another scale than the background's,
    so the static videos it would pose stay unposed, and say why (tests/sfm/test_subject_posed.py: with tracks)."""
    plans = [_plan(tmp_path, "anchor", True), _plan(tmp_path, "free", True), _plan(tmp_path, "hand", False)]
    pose = FramePose(pose=pycolmap.Rigid3d(), source="sfm")
    results = {
        "anchor": dict.fromkeys(range(30), pose),
        "free": {f: FramePose(pose=None, reason="not in the background model") for f in range(30)},
        "hand": dict.fromkeys(range(30), pose),
    }
    warnings: list[str] = []

    section = pose_from_subject(plans, results, _tracks(["anchor", "free"]), {}, RegisterOptions(), warnings)

    assert section is not None and not section["used"] and section["anchors"] == ["anchor"]
    assert "not its scale" in section["why"] and "(hand)" in section["why"]
    assert all(r.pose is None and "not its scale" in r.reason for r in results["free"].values())
    assert results["anchor"][0].pose is not None and results["hand"][0].pose is not None
    assert len(warnings) == 1 and "track the subject in a video the background posed" in warnings[0]


def test_no_anchor_beside_background_cameras_is_refused(tmp_path: Path) -> None:
    """The background posed only a handheld video, which has no tracks: the subject path's static cameras would be in
    a frame of their own, beside it."""
    plans = [_plan(tmp_path, "left", True), _plan(tmp_path, "right", True), _plan(tmp_path, "hand", False)]
    unposed = {f: FramePose(pose=None, reason="not in the background model") for f in range(30)}
    results = {
        "left": dict(unposed),
        "right": dict(unposed),
        "hand": dict.fromkeys(range(30), FramePose(pose=pycolmap.Rigid3d(), source="sfm")),
    }
    warnings: list[str] = []

    section = pose_from_subject(plans, results, _tracks(["left", "right"]), {}, RegisterOptions(), warnings)

    assert section is not None and not section["used"] and section["anchors"] == []
    assert "another frame and scale" in section["why"] and "(hand)" in section["why"]
    assert all(r.pose is None for name in ("left", "right") for r in results[name].values())


def test_two_self_calibrated_cameras_alone_are_refused_before_any_solve(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two static videos with no intrinsics and nothing else posed: the pair cannot fix its focals, so the path is
    refused at once (no solve: the folds would refuse it a minute later) naming what to give; with one camera's
    intrinsics known it is solved."""
    import sfm.register_subject as register_subject

    def no_solve(*_: object) -> None:
        raise AssertionError("solved")

    monkeypatch.setattr(register_subject, "choose_noise", no_solve)
    plans = [_plan(tmp_path, name, True) for name in ("a", "b")]
    results = {n: {f: FramePose(pose=None, reason="not in the background model") for f in range(30)} for n in "ab"}
    warnings: list[str] = []
    section = pose_from_subject(plans, results, _tracks(["a", "b"]), {}, RegisterOptions(), warnings)
    assert section is not None and not section["used"] and "--intrinsics, --board, or a third video" in section["why"]
    assert all("two cameras with self-calibrated focal" in r.reason for r in results["a"].values())
    with pytest.raises(AssertionError, match="solved"):
        known = {n: (np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), None) for n in "ab"}
        pose_from_subject(plans, results, _tracks(["a", "b"]), known, RegisterOptions(), warnings)


def test_two_static_videos_without_tracks_are_told_both_things_they_need(tmp_path: Path) -> None:
    """Two static videos that the background left out, with no tracks and no intrinsics (a two-camera sports
    capture): the advice names labeling and tracking and, at once, the intrinsics the pair will also need; with
    intrinsics given, or a third video, only the tracks."""
    unposed = {f: FramePose(pose=None, reason="not in the background model") for f in range(30)}
    options = RegisterOptions(find_markers=False)
    plans = [_plan(tmp_path, name, True) for name in ("a", "b")]
    section = pose_from_subject(plans, {n: dict(unposed) for n in "ab"}, None, {}, options, [])
    assert section is not None and "dynrecon label" in section["why"] and "dynrecon track" in section["why"]
    assert "two static videos also need their intrinsics (--intrinsics FILE)" in section["why"]
    known = {n: (np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), None) for n in "ab"}
    section = pose_from_subject(plans, {n: dict(unposed) for n in "ab"}, None, known, options, [])
    assert section is not None and "dynrecon track" in section["why"] and "--intrinsics" not in section["why"]
    three = [*plans, _plan(tmp_path, "c", True)]
    section = pose_from_subject(three, {n: dict(unposed) for n in "abc"}, None, {}, options, [])
    assert section is not None and "--intrinsics" not in section["why"]


def test_a_solve_whose_cameras_are_all_unstable_says_why(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The subject path ran, but no camera it posed is determined by the tracks (e.g. a detector that follows other
    people in other views): the section says why, for the command's one-line error, and no frame is posed."""
    import sfm.register_subject as register_subject

    names = ["a", "b", "c"]
    plans = [_plan(tmp_path, name, True) for name in names]
    results = {n: {f: FramePose(pose=None, reason="not in the background model") for f in range(30)} for n in names}
    cameras = [
        SubjectCamera(name=n, K=np.eye(3), dist=None, R=np.eye(3), t=np.zeros(3), offset=0.0, inliers=50, residual_px=1)
        for n in names
    ]
    unstable = {n: "not determined by the tracks: its centre moves by 30 % of the camera spread" for n in names}

    def solved(*_: object) -> tuple[SubjectResult, Stability]:
        return SubjectResult(cameras=cameras, pairs=[], failed={}, metric=False), Stability(unstable=unstable)

    monkeypatch.setattr(register_subject, "choose_noise", solved)
    warnings: list[str] = []

    section = pose_from_subject(plans, results, _tracks(names), {}, RegisterOptions(), warnings)

    assert section is not None and section["posed"] == []
    assert "posed no video that its tracks determine (a, b, c: not determined" in section["why"]  # one reason, once
    assert all(r.pose is None for name in names for r in results[name].values())


def test_a_video_set_aside_is_unposed_and_said(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Solved together no camera is determined; without d the other three are: d is set aside, its background pose
    (--subject always: not an anchor, and in another world frame than the subject path's) is not kept, and a
    warning and the section say so."""
    import sfm.register_subject as register_subject
    from sfm.options import SubjectPath

    names = ["a", "b", "c", "d"]
    plans = [_plan(tmp_path, name, True) for name in names]
    results = {n: {f: FramePose(pose=None, reason="not in the background model") for f in range(30)} for n in names}
    results["d"] = {f: FramePose(pose=pycolmap.Rigid3d(), source="sfm") for f in range(30)}

    def solved(tracks: Tracks, videos: list, options: object) -> tuple[SubjectResult, Stability]:
        group = [v.name for v in videos]
        cameras = _cameras_apart(group)
        moves = {n: [(0.9 if n == "d" else 0.4) if "d" in group else 0.01] for n in group}
        unstable = {n: "not determined by the tracks: its centre moves by 40 %" for n in group if "d" in group}
        stability = Stability(centre_folds=moves, rotation_folds={n: [0.5] for n in group}, unstable=unstable)
        return SubjectResult(cameras=cameras, pairs=[], failed={}, metric=False), stability

    monkeypatch.setattr(register_subject, "choose_noise", solved)
    warnings: list[str] = []
    known = {n: (np.diag([500.0, 500.0, 1.0]), None) for n in names}

    options = RegisterOptions(subject=SubjectPath.ALWAYS)
    section = pose_from_subject(plans, results, _tracks(names), known, options, warnings)

    assert section is not None and section["posed"] == ["a", "b", "c"] and section["set_aside"] == ["d"]
    assert all(r.pose is None and "set aside" in (r.reason or "") for r in results["d"].values())
    assert any(w.startswith("d: subject path: set aside: solved with the other videos") for w in warnings)


def test_videos_left_unposed_name_the_offset_search_and_max_offset(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Clock offsets are searched within ±max_offset: videos that run longer than that (a drone filmed for minutes,
    cameras started 33 s apart) may be unposed for it; the warning names --max-offset, which the path receives."""
    import dataclasses

    import sfm.register_subject as register_subject

    names = ["a", "b", "c"]
    plans = []
    for name in names:
        plan = _plan(tmp_path, name, True)
        plans.append(dataclasses.replace(plan, info=dataclasses.replace(plan.info, times=np.arange(900) / 30.0)))
    results = {n: {f: FramePose(pose=None, reason="not in the background model") for f in range(30)} for n in names}
    seen: list[float] = []

    def solved(tracks: Tracks, videos: list, options: object) -> tuple[SubjectResult, Stability]:
        seen.append(options.max_offset)  # type: ignore[attr-defined]
        cameras = _cameras_apart(["a", "b"])
        return SubjectResult(cameras=cameras, pairs=[], failed={"c": "no usable pair"}, metric=False), Stability()

    monkeypatch.setattr(register_subject, "choose_noise", solved)
    known = {n: (np.diag([500.0, 500.0, 1.0]), None) for n in names}
    warnings: list[str] = []
    section = pose_from_subject(plans, results, _tracks(names), known, RegisterOptions(), warnings)
    assert section is not None and section["posed"] == ["a", "b"] and seen == [10.0]
    hint = [w for w in warnings if "--max-offset" in w]
    assert hint == [
        "subject path: c not posed, and two videos' clock offset is searched within ±10 s while the videos run up "
        "to 30 s: if their cameras were started further apart, register again with --max-offset 30"
    ]
    warnings.clear()
    pose_from_subject(plans, results, _tracks(names), known, RegisterOptions(max_offset=40.0), warnings)
    assert seen[-1] == 40.0 and not [w for w in warnings if "--max-offset" in w]

    # refused for another reason than its pairs (its poses moved between folds): a farther search would not help
    def unstable(tracks: Tracks, videos: list, options: object) -> tuple[SubjectResult, Stability]:
        cameras = _cameras_apart(["a", "b"])
        failed = {"c": "not determined by the tracks: its pose moves 30 deg between folds"}
        return SubjectResult(cameras=cameras, pairs=[], failed=failed, metric=False), Stability()

    monkeypatch.setattr(register_subject, "choose_noise", unstable)
    warnings.clear()
    pose_from_subject(plans, results, _tracks(names), known, RegisterOptions(), warnings)
    assert not [w for w in warnings if "--max-offset" in w]


def test_posed_cameras_the_folds_turn_by_degrees_are_said_to_be_uncertain() -> None:
    from sfm.register_subject import UNCERTAIN_DEG, _warn_uncertain

    stability = Stability(rotation_folds={"a": [0.4], "b": [UNCERTAIN_DEG + 1.7], "c": [9.0]})
    warnings: list[str] = []
    _warn_uncertain(stability, ["a", "b"], warnings)  # c was not posed (refused as unstable elsewhere)
    assert (
        len(warnings) == 1 and "b by 3.7 deg" in warnings[0] and "a by" not in warnings[0] and "c by" not in warnings[0]
    )
    _warn_uncertain(Stability(rotation_folds={"a": [0.4]}), ["a"], warnings)
    assert len(warnings) == 1


def test_fitted_offsets_are_compared_with_the_declared(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each pair's claim is judged before the pairs are chained: the section also says, per camera after the
    adjustment, how far its offset ended from the declared one (in the declared offsets' gauge), and warns past a
    frame."""
    import sfm.register_subject as register_subject

    names = ["a", "b", "c"]
    plans = [_plan(tmp_path, name, True) for name in names]
    results = {n: {f: FramePose(pose=None, reason="not in the background model") for f in range(30)} for n in names}
    fitted = {"a": 2.0, "b": 2.5, "c": 2.01}  # any common origin; b half a second from the declared 0
    cameras = [
        SubjectCamera(
            name=n, K=np.eye(3), dist=None, R=np.eye(3), t=np.full(3, k), offset=fitted[n], inliers=50, residual_px=1
        )
        for k, n in enumerate(names)
    ]

    def solved(*_: object) -> tuple[SubjectResult, Stability]:
        return SubjectResult(cameras=cameras, pairs=[], failed={}, metric=False), Stability(checked=True)

    monkeypatch.setattr(register_subject, "choose_noise", solved)
    warnings: list[str] = []

    section = pose_from_subject(plans, results, _tracks(names), {}, RegisterOptions(synchronized=True), warnings)

    assert section is not None and section["declared"]["agree"] is False
    rows = {row["name"]: row for row in section["declared"]["cameras"]}
    assert rows["a"]["agree"] and rows["c"]["agree"] and not rows["b"]["agree"]
    assert rows["b"]["difference_s"] == pytest.approx(0.49)
    assert rows["b"]["tolerance_s"] == pytest.approx(1 / 30, abs=1e-6)
    assert any("--synchronized: fitted clock offsets over a frame" in w and "b +0.490 s" in w for w in warnings)
    # no intrinsics given: the poses rest on a principal point at each image's centre, which the folds cannot see
    assert any(w.startswith("subject path: a, b, c: intrinsics self-calibrated") for w in warnings)

    warnings.clear()
    cameras[1].offset = 2.02
    results = {n: {f: FramePose(pose=None, reason="not in the background model") for f in range(30)} for n in names}
    known = {n: (np.diag([500.0, 500.0, 1.0]), None) for n in names}
    section = pose_from_subject(plans, results, _tracks(names), known, RegisterOptions(synchronized=True), warnings)
    assert section is not None and section["declared"]["agree"] is True
    assert not any("over a frame" in w or "self-calibrated" in w for w in warnings)


def test_two_declared_cameras_are_judged_as_a_pair(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With two cameras the median gauge would put half of one camera's error on each (1.5 frames: 0.75 each, both
    "agreeing"); the pair's whole difference is judged instead."""
    import sfm.register_subject as register_subject

    names = ["a", "b"]
    plans = [_plan(tmp_path, name, True) for name in names]
    results = {n: {f: FramePose(pose=None, reason="not in the background model") for f in range(30)} for n in names}
    cameras = [
        SubjectCamera(name=n, K=np.eye(3), dist=None, R=np.eye(3), t=np.full(3, k), offset=o, inliers=50, residual_px=1)
        for k, (n, o) in enumerate(zip(names, [2.0, 2.05], strict=True))
    ]
    monkeypatch.setattr(
        register_subject,
        "choose_noise",
        lambda *_: (SubjectResult(cameras=cameras, pairs=[], failed={}, metric=False), Stability(checked=True)),
    )
    warnings: list[str] = []
    known = {n: (np.eye(3), None) for n in names}  # two self-calibrated cameras would be refused before the solve
    section = pose_from_subject(plans, results, _tracks(names), known, RegisterOptions(synchronized=True), warnings)
    assert section is not None and section["declared"]["agree"] is False
    rows = {row["name"]: row for row in section["declared"]["cameras"]}
    assert rows["b"]["difference_s"] == pytest.approx(0.05) and not rows["a"]["agree"] and not rows["b"]["agree"]
    assert any("b +0.050 s from a" in w and "cannot be told" in w for w in warnings)
