"""Clock recovery from W's links: synthetic captures with known clocks (offset, rate, drift) and an ideal W built
from the true times, with outlier links; JSON round trip; the solver end to end on a small capture."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
import pytest
import scipy.sparse as sp

from dynrecon.errors import InputError
from reconstruct.clocks.estimate import ClockOptions, SearchMode, estimate_clocks, fit_links
from reconstruct.clocks.model import (
    Clock,
    ClockCorrection,
    ClockModel,
    Clocks,
    ClockSet,
    TimeSource,
    VideoClockReport,
    own_times,
)
from reconstruct.solver.alternation import SolverOptions, solve
from reconstruct.solver.problem import Problem


@dataclass(kw_only=True)
class ClockTruth:
    fps: float
    frames: int
    offset: float = 0.0  # global = offset + rate * own + drift * own^2
    rate: float = 1.0
    drift: float = 0.0


def trajectory(g: np.ndarray, points: int, seed: int, drone: bool) -> np.ndarray:
    """(T, P, 3) m: a smooth body (points on a swaying, turning ~1 m shape) or one drone point (tens of metres)."""
    rng = np.random.default_rng(seed)
    g = np.asarray(g, dtype=float)
    if drone:
        f = rng.uniform(0.03, 0.08, size=3)
        phase = rng.uniform(0, 2 * np.pi, size=3)
        amp = np.array([25.0, 20.0, 6.0])
        c = amp * np.sin(2 * np.pi * f * g[:, None] + phase) + np.array([0.0, 0.0, 25.0])
        return c[:, None, :]
    base = rng.normal(size=(points, 3)) * 0.4
    centre = np.stack([1.5 * np.sin(0.4 * g + 0.3), 1.0 * np.sin(0.55 * g + 1.0), 1.0 + 0.2 * np.sin(1.3 * g)], axis=1)
    angle = 0.8 * g
    c, s = np.cos(angle), np.sin(angle)
    rotated = np.stack(
        [
            c[:, None] * base[None, :, 0] - s[:, None] * base[None, :, 1],
            s[:, None] * base[None, :, 0] + c[:, None] * base[None, :, 1],
            np.broadcast_to(base[None, :, 2], (len(g), points)),
        ],
        axis=-1,
    )
    wobble = 0.1 * np.sin(2 * np.pi * 1.1 * g[:, None, None] + base[None] * 3)
    return centre[:, None, :] + rotated + wobble


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """cam_from_world rotation of a camera at `centre` looking at `target`, z up in the world."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def make_capture(
    clocks: list[ClockTruth],
    *,
    points: int = 6,
    distance: float = 8.0,
    noise_px: float = 0.5,
    seed: int = 0,
    drone: bool = False,
    handheld: bool = False,
    decoder_times: bool = True,
    outlier_share: float = 0.0,
) -> tuple[Problem, np.ndarray, np.ndarray]:
    """A Problem of len(clocks) cameras on a ring around the motion; returns (problem, true global time (F,),
    true points (F, P, 3)). Outliers: that share of observations replaced by random pixels."""
    rng = np.random.default_rng(seed + 1)
    K = np.array([[1500.0, 0, 959.5], [0, 1500.0, 539.5], [0, 0, 1]])
    own_l, glob_l, vid_l, frm_l = [], [], [], []
    for v, clock in enumerate(clocks):
        own = np.arange(clock.frames) / clock.fps
        own_l.append(own)
        glob_l.append(clock.offset + clock.rate * own + clock.drift * own**2)
        vid_l.append(np.full(clock.frames, v))
        frm_l.append(np.arange(clock.frames))
    own, g = np.concatenate(own_l), np.concatenate(glob_l)
    video_index, frames = np.concatenate(vid_l), np.concatenate(frm_l)
    X = trajectory(g, points, seed, drone)
    F, P = X.shape[:2]
    target = np.array([0.0, 0.0, 25.0 if drone else 1.0])
    R = np.empty((F, 3, 3))
    t = np.empty((F, 3))
    for v in range(len(clocks)):
        azimuth = 2 * np.pi * v / len(clocks) + rng.uniform(-0.3, 0.3)
        rows = np.flatnonzero(video_index == v)
        centre = np.array([distance * np.cos(azimuth), distance * np.sin(azimuth), 1.5])
        for i in rows:
            c = centre.copy()
            aim = target.copy()
            if handheld:
                c += 0.05 * np.sin(np.array([1.3, 1.7, 2.1]) * g[i] + v)
                aim += 0.3 * np.sin(np.array([0.7, 0.9, 0.5]) * g[i] + 2 * v)
            R[i] = look_at(c, aim)
            t[i] = -R[i] @ c
    cam = np.einsum("fij,fpj->fpi", R, X) + t[:, None, :]
    uv = np.einsum("ij,fpj->fpi", K, cam)
    uv = uv[..., :2] / uv[..., 2:3] + rng.normal(scale=noise_px, size=(F, P, 2))
    if outlier_share > 0:
        bad = rng.random((F, P)) < outlier_share
        uv[bad] = rng.uniform([0, 0], [1920, 1080], size=(int(bad.sum()), 2))
    problem = Problem(
        video_names=[f"cam{v}" for v in range(len(clocks))],
        video_index=video_index,
        frames=frames,
        times=own if decoder_times else np.full(F, np.nan),
        point_names=[f"p{p}" for p in range(P)],
        K=np.broadcast_to(K, (F, 3, 3)).copy(),
        R=R,
        t=t,
        dist=[None] * F,
        uv=uv,
    )
    return problem, g, X


def ideal_w(video_index: np.ndarray, g: np.ndarray, seed: int, outliers: float = 0.0) -> sp.csc_matrix:
    """W from the true times: each frame is interpolated between the two bracketing frames of one or two other
    videos; `outliers` of the columns link a random frame of another video instead."""
    rng = np.random.default_rng(seed)
    F = len(g)
    rows, cols, vals = [], [], []
    videos = np.unique(video_index)
    for f in range(F):
        if rng.random() < outliers:
            others = np.flatnonzero(video_index != video_index[f])
            rows.append(int(rng.choice(others)))
            cols.append(f)
            vals.append(1.0)
            continue
        brackets = []
        for u in videos:
            if u == video_index[f]:
                continue
            idx = np.flatnonzero(video_index == u)
            times = g[idx]
            k = np.searchsorted(times, g[f])
            if 0 < k < len(idx):
                a = (g[f] - times[k - 1]) / (times[k] - times[k - 1])
                brackets.append([(idx[k - 1], 1 - a), (idx[k], a)])
        if not brackets:
            continue
        chosen = rng.permutation(len(brackets))[:2]
        for c in chosen:
            for j, w in brackets[c]:
                rows.append(int(j))
                cols.append(f)
                vals.append(w / len(chosen))
    return sp.csc_matrix((vals, (rows, cols)), shape=(F, F))


PHONES = [
    ClockTruth(fps=30.0, frames=240),
    ClockTruth(fps=24.0, frames=200, offset=1.37, rate=1.0004),
    ClockTruth(fps=60.0, frames=420, offset=-0.82, rate=0.9997),
    ClockTruth(fps=25.0, frames=210, offset=0.511, rate=1.0002),
]


def clock_errors(problem: Problem, g: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    return np.abs(estimate - g)


def test_own_times_sources() -> None:
    problem, _, _ = make_capture(PHONES[:2], points=2)
    problem.times[problem.video_index == 1] = np.nan
    problem.times[3] = np.nan  # one missing decoder time in cam0 is filled from the line time ~ frame
    own, sources = own_times(problem, {"cam1": 24.0})
    assert sources == [TimeSource.DECODER, TimeSource.FPS]
    assert own[3] == pytest.approx(3 / 30.0)
    assert own[problem.video_index == 1][10] == pytest.approx(10 / 24.0)
    _, sources = own_times(problem)
    assert sources[1] is TimeSource.NOMINAL


@pytest.mark.parametrize("model", [ClockModel.OFFSET, ClockModel.AFFINE])
def test_links_recover_clocks_with_outliers(model: ClockModel) -> None:
    clocks = (
        PHONES
        if model is ClockModel.AFFINE
        else [ClockTruth(fps=c.fps, frames=c.frames, offset=c.offset) for c in PHONES]
    )
    problem, g, _ = make_capture(clocks, points=2)
    W = ideal_w(problem.video_index, g, seed=1, outliers=0.2)
    own, _ = own_times(problem)
    fit = fit_links(W, own, problem.video_index, len(clocks), 0, model)
    assert fit.params.identified.all()
    error = np.abs(fit.params.global_time(own, problem.video_index) - g)
    assert np.median(error) < 0.25 / 60.0
    assert np.max(error) < 0.5 / 60.0
    for v, clock in enumerate(clocks):
        values, stds = fit.params.offset_rate_drift(v)
        assert values[0] == pytest.approx(clock.offset, abs=0.004)
        assert values[1] == pytest.approx(clock.rate, abs=3e-4)
        if v:
            assert 0 < stds[0] < 0.01
    assert 0.7 < fit.inlier_share < 0.9  # the 20 % outlier columns are rejected


def test_links_drift_model() -> None:
    clocks = [
        ClockTruth(fps=30.0, frames=600),
        ClockTruth(fps=25.0, frames=500, offset=0.3, rate=1.001, drift=4e-4),
        ClockTruth(fps=50.0, frames=1000, offset=-0.4, rate=0.999),
    ]
    problem, g, _ = make_capture(clocks, points=2)
    W = ideal_w(problem.video_index, g, seed=2, outliers=0.1)
    own, _ = own_times(problem)
    affine = fit_links(W, own, problem.video_index, 3, 0, ClockModel.AFFINE)
    drift = fit_links(W, own, problem.video_index, 3, 0, ClockModel.DRIFT)
    error_affine = np.abs(affine.params.global_time(own, problem.video_index) - g)
    error_drift = np.abs(drift.params.global_time(own, problem.video_index) - g)
    assert np.max(error_drift) < 0.25 / 50.0
    assert np.median(error_drift) < 0.5 * np.median(error_affine)
    values, stds = drift.params.offset_rate_drift(1)
    assert abs(values[2] - 4e-4) < 4 * stds[2] + 1e-5


def test_unlinked_video_is_not_identified() -> None:
    problem, g, _ = make_capture(PHONES[:3], points=2)
    W = ideal_w(problem.video_index, g, seed=3).tolil()
    cam2 = np.flatnonzero(problem.video_index == 2)
    W[cam2, :] = 0  # nobody uses cam2's frames ...
    W[:, cam2] = 0  # ... and cam2's frames use nobody
    own, _ = own_times(problem)
    fit = fit_links(W.tocsc(), own, problem.video_index, 3, 0, ClockModel.AFFINE, ["cam0", "cam1", "cam2"])
    assert list(fit.params.identified) == [True, True, False]
    assert any("cam2" in w and "not identified" in w for w in fit.warnings)


class _FakeW:
    def __init__(self, W: sp.csc_matrix):
        self._W = W

    def to_csc(self) -> sp.csc_matrix:
        return self._W


class _FakeResult:
    """What estimate_clocks reads of a SolveResult: W and the reconstructable points."""

    def __init__(self, W: sp.csc_matrix, P: int):
        self.W = _FakeW(W)
        self.reconstructable = np.ones(P, dtype=bool)


def test_json_round_trip_and_errors() -> None:
    problem, g, _ = make_capture(PHONES[:3], points=8, distance=6.0)
    W = ideal_w(problem.video_index, g, seed=4, outliers=0.1)
    clocks = estimate_clocks(problem, _FakeResult(W, 8), ClockOptions(search=SearchMode.NEVER))  # type: ignore[arg-type]
    document = json.loads(json.dumps(clocks.to_json()))
    back = Clocks.from_json(document)
    assert back.reference == "cam0" and back.model is ClockModel.AFFINE
    assert [v.name for v in back.videos] == problem.video_names
    np.testing.assert_allclose(back.global_time, clocks.global_time, equal_nan=True)
    np.testing.assert_allclose(back.global_std, clocks.global_std, equal_nan=True)
    assert back.video("cam1").offset == clocks.video("cam1").offset
    assert back.video("cam1").offset == pytest.approx(PHONES[1].offset, abs=0.004)
    assert 0 < back.video("cam1").offset_std < 0.01
    # Every frame's std includes at least the interpolation floor (1/20 of its video's frame period).
    assert np.all(back.global_std[problem.video_index == 2] >= 0.05 / 60.0 - 1e-12)
    del document["videos"][0]["rate"]
    with pytest.raises(InputError, match=r"sequencing\.json"):
        Clocks.from_json(document, "sequencing.json")


def test_unidentified_video_has_no_times() -> None:
    problem, g, _ = make_capture(PHONES[:3], points=2)
    W = ideal_w(problem.video_index, g, seed=3).tolil()
    cam2 = np.flatnonzero(problem.video_index == 2)
    W[cam2, :] = 0
    W[:, cam2] = 0
    clocks = estimate_clocks(
        problem,
        _FakeResult(W.tocsc(), 8),  # type: ignore[arg-type]
        ClockOptions(search=SearchMode.NEVER),
    )
    cam2_clock = clocks.video("cam2")
    assert not cam2_clock.identified and cam2_clock.method == "unidentified" and math.isnan(cam2_clock.offset)
    assert np.all(np.isnan(clocks.global_time[cam2]))
    assert clocks.to_json()["videos"][2]["offset"] is None
    assert any("cam2" in w for w in clocks.warnings)


def test_estimate_clocks_after_solve() -> None:
    """The real solver's W on a small body capture: clocks within a quarter of the fastest frame period."""
    clocks = [
        ClockTruth(fps=30.0, frames=60),
        ClockTruth(fps=24.0, frames=50, offset=0.213, rate=1.0),
        ClockTruth(fps=20.0, frames=40, offset=-0.171, rate=1.0),
    ]
    problem, g, _ = make_capture(clocks, points=8, distance=5.0, noise_px=0.3, seed=4)
    result = solve(problem, SolverOptions(max_iterations=30))
    estimate = estimate_clocks(problem, result, ClockOptions(search=SearchMode.NEVER))
    overlap = (g > 0.25) & (g < 1.7)
    error = np.abs(estimate.global_time - g)[overlap]
    assert np.median(error) < 0.25 / 30.0
    assert all(v.identified for v in estimate.videos)
    assert estimate.videos[0].method == "reference" and estimate.videos[1].method == "links"


def test_clock_model_inverse_report_form_and_set() -> None:
    """One clock: own -> global and back (Newton with a drift term), the report form at own time 0, and a ClockSet
    evaluating the same clocks per frame."""
    clock = Clock(center=2.0, coef=np.array([3.1, 1.0004, 2e-4]), cov=np.diag([1e-6, 1e-8, 1e-10]))
    own = np.linspace(0.0, 4.0, 9)
    np.testing.assert_allclose(clock.own_time(clock.global_time(own)), own, atol=1e-12)
    values, stds = clock.offset_rate_drift()
    offset, rate, drift = values
    np.testing.assert_allclose(offset + rate * own + drift * own**2, clock.global_time(own), atol=1e-12)
    assert np.all(stds > 0)
    affine = Clock.affine(0.25, 1.001)
    assert affine.global_time(np.array([2.0]))[0] == 0.25 + 1.001 * 2.0
    assert affine.own_time(np.array([0.25]))[0] == 0.0
    clocks = ClockSet.reference_only(np.array([1.0, 2.0]), 0)
    clocks.coef[1], clocks.cov[1], clocks.identified[1] = clock.coef, clock.cov, True
    video_index = np.array([0, 0, 1, 1])
    frames_own = np.array([0.5, 1.5, 1.0, 3.0])
    times = clocks.global_time(frames_own, video_index)
    np.testing.assert_allclose(times[:2], frames_own[:2])  # the reference's clock is the identity
    np.testing.assert_allclose(times[2:], clock.global_time(frames_own[2:]))
    assert np.all(clocks.global_std(frames_own, video_index)[:2] == 0)


def test_clock_correction_fit_and_gauge() -> None:
    """A correction fitted from its own result is recovered, and re-gauged it leaves the reference video alone."""
    video_index = np.repeat([0, 1, 2], 50)
    times = np.concatenate([np.linspace(0, 2, 50), np.linspace(0.3, 2.1, 50), np.linspace(-0.2, 1.5, 50)])
    middle = np.array([np.median(times[video_index == v]) for v in range(3)])
    truth = ClockCorrection(middle=middle, offset=np.array([0.002, -0.004, 0.001]), rate=np.array([1e-3, 0, -2e-3]))
    moved = truth.apply(times, video_index)
    fitted = ClockCorrection.fit(times, moved, video_index, 3)
    np.testing.assert_allclose(fitted.offset, truth.offset, atol=1e-12)
    np.testing.assert_allclose(fitted.rate, truth.rate, atol=1e-12)
    adjusted, gauged = truth.in_gauge_of(0, times, video_index)
    assert gauged.offset[0] == pytest.approx(0.0, abs=1e-15) and gauged.rate[0] == pytest.approx(0.0, abs=1e-15)
    np.testing.assert_allclose(adjusted[video_index == 0], times[video_index == 0], atol=1e-12)
    np.testing.assert_allclose(gauged.apply(times, video_index), adjusted, atol=1e-12)


def test_a_refit_widens_the_uncertainty_by_its_move() -> None:
    """The trajectories' polish moved real rigs' clocks 0.2-1 frame from estimates stated to 0.01-0.03 frame (a bat
    rig's cam3: 0.356 +- 0.012 frame where the truth is 0): the move counts in the stated uncertainty."""
    own = np.tile(np.arange(10) / 100.0, 2)
    index = np.repeat([0, 1], 10)
    videos = [
        VideoClockReport(
            name="a",
            time_source=TimeSource.DECODER,
            offset=0.0,
            rate=1.0,
            offset_std=0.0,
            method="reference",
            identified=True,
        ),
        VideoClockReport(
            name="b",
            time_source=TimeSource.DECODER,
            offset=0.5,
            rate=1.0,
            offset_std=0.0001,
            method="tracks",
            identified=True,
        ),
    ]
    times = own + np.where(index == 1, 0.5, 0.0)
    clocks = Clocks(
        model=ClockModel.OFFSET,
        reference="a",
        videos=videos,
        frame_videos=["a"] * 10 + ["b"] * 10,
        frames=np.tile(np.arange(10), 2),
        own_time=own,
        global_time=times.copy(),
        global_std=np.full(20, 0.0001),
    )
    polished = times + np.where(index == 1, 0.004, 0.0)  # b's clock moved by 4 ms
    clocks.refit(index, polished)
    assert clocks.video("b").offset == pytest.approx(0.504)
    assert clocks.video("b").offset_std == pytest.approx(math.hypot(0.0001, 0.004))
    assert clocks.video("a").offset_std == pytest.approx(0.0, abs=1e-15)  # the reference did not move
    np.testing.assert_allclose(clocks.global_std[index == 1], math.hypot(0.0001, 0.004))
    np.testing.assert_allclose(clocks.global_std[index == 0], 0.0001)
    # the agreement with registered or declared offsets is judged on the estimate's own std: b's 4 ms move must
    # not let an offset 4 ms from the solve's agree (3 x the widened std would)
    from reconstruct.clocks.registered import check_registered_clocks
    from sfm.cameras import CameraSet, VideoCameras

    assert clocks.video("b").estimate_std == 0.0001
    cameras = CameraSet(
        videos=[
            VideoCameras(name=name, width=10, height=10, fps=1000.0, clock_offset=offset)
            for name, offset in (("a", 0.0), ("b", 0.5))
        ]
    )
    check = check_registered_clocks(cameras, clocks)
    assert check is not None and not check["agree"] and check["videos"][0]["tolerance_s"] == pytest.approx(0.001)


def test_registered_offsets_are_compared_where_the_frames_are() -> None:
    """A fitted rate moves a clock's offset at own time 0 away from registration's (rate 1) without any
    disagreement where the video's frames are: a phone 0.1 % slow over 8-10 min differs 0.5 s at own time 0."""
    from reconstruct.clocks.model import ClockModel, Clocks, TimeSource, VideoClockReport
    from reconstruct.clocks.registered import check_registered_clocks
    from sfm.cameras import CameraSet, FrameCamera, VideoCameras

    def clock(name: str, offset: float, rate: float) -> VideoClockReport:
        return VideoClockReport(
            name=name, time_source=TimeSource.FPS, offset=offset, rate=rate, offset_std=0.001, identified=True
        )

    middle = 500.0  # own s: frames 0-30,000 at 30 fps
    frames = [FrameCamera(frame=k, K=np.eye(3), R=np.eye(3), t=np.zeros(3)) for k in (0, 15_000, 30_000)]
    cameras = CameraSet(
        videos=[
            VideoCameras(name=n, width=10, height=10, fps=30.0, frames=frames, clock_offset=o)
            for n, o in (("a", 0.0), ("b", 2.0))
        ]
    )
    slow = clock("b", 2.0 - 0.001 * middle, 1.001)  # the same offset as registration's in the middle
    empty = np.zeros(0)
    clocks = Clocks(
        model=ClockModel.AFFINE,
        reference="a",
        videos=[clock("a", 0.0, 1.0), slow],
        frame_videos=[],
        frames=empty,
        own_time=empty,
        global_time=empty,
        global_std=empty,
    )
    check = check_registered_clocks(cameras, clocks)
    assert check is not None and check["agree"], check
    assert check["videos"][0]["difference_s"] == pytest.approx(0.0, abs=1e-9)
