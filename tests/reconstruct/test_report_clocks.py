"""report.json `clocks.used`: the clocks a solve did not rest its points on are said to be unused, with the check
they failed, so that their offsets are not read as a result."""

from __future__ import annotations

from reconstruct.stage import _say_unused_clocks


def _checks(distinctness: float) -> list[dict[str, object]]:
    return [
        {"name": "identified", "value": 0.0, "limit": 0.0, "passed": True, "meaning": "videos unclocked"},
        {
            "name": "track_distinctness",
            "value": distinctness,
            "limit": 1.05,
            "passed": distinctness >= 1.05,
            "meaning": "track search's runner-up cost over its best",
        },
    ]


def test_clocks_that_failed_their_check_are_said_unused() -> None:
    clocks: dict[str, object] = {"warnings": ["cam2: few links"]}
    _say_unused_clocks(clocks, {"path": "seed", "checks": _checks(1.015)})
    assert clocks["used"] is False
    assert clocks["warnings"][0] == "cam2: few links"  # type: ignore[index]
    said = clocks["warnings"][1]  # type: ignore[index]
    assert said.startswith("not used: the clocks' check 'track_distinctness' failed: ")
    assert "1.01 (limit >= 1.05)" in said and "not a result the points rest on" in said


def test_clocks_of_a_solve_without_refinement_are_said_unused() -> None:
    clocks: dict[str, object] = {"warnings": []}
    _say_unused_clocks(clocks, {"path": "seed", "refinement": "none"})
    assert clocks["used"] is False
    assert clocks["warnings"] == [  # type: ignore[comparison-overlap]
        "not used: the refinement was off (--refinement none), and the points are the self-expressive solve's; the "
        "offsets are the clock estimate's best guess, not a result the points rest on"
    ]


def test_clocks_the_points_rest_on_are_used() -> None:
    for path in ("clocks", "free_times", "tracks"):
        clocks: dict[str, object] = {"warnings": []}
        _say_unused_clocks(clocks, {"path": path, "checks": _checks(4.0)})
        assert clocks == {"warnings": [], "used": True}


def test_a_solve_without_a_single_recovered_clock_names_the_usual_cause() -> None:
    """Every video but the reference unclocked and the seed solve kept (Pose2Sim's two-person trial imported with
    `--person 1`, another person in some views): one warning says the points may be far off and why, where the
    per-video clock lines did not."""
    import numpy as np

    from reconstruct.clocks.model import ClockModel, Clocks, TimeSource, VideoClockReport
    from reconstruct.temporal import _warn_no_clock

    def clocks(identified: bool) -> Clocks:
        videos = [VideoClockReport(name="cam01", time_source=TimeSource.FPS, method="reference", identified=True)]
        videos += [
            VideoClockReport(name=n, time_source=TimeSource.FPS, identified=identified) for n in ("cam02", "cam03")
        ]
        empty = np.zeros(0)
        return Clocks(
            model=ClockModel.OFFSET,
            reference="cam01",
            videos=videos,
            frame_videos=[],
            frames=empty,
            own_time=empty,
            global_time=empty,
            global_std=empty,
        )

    none, some = clocks(False), clocks(True)
    _warn_no_clock(none)
    _warn_no_clock(some)
    assert len(none.warnings) == 1 and not some.warnings
    assert none.warnings[0].startswith("no video's clock was recovered against 'cam01' (cam02, cam03)")
    assert "--person all" in none.warnings[0]
