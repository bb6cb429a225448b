"""Registration's clock offsets as a second clock hypothesis (issue 16: "the recovered offsets become a prior for
the solver's clocks").

Register's subject path fits each static video's clock offset from the subject's 2D tracks and the epipolar
geometry, and writes it to cameras.json (`clock_offset`). The solve recovers clocks from its own evidence (W's
links, the track search). Where the two disagree (`clocks.registered.check_registered_clocks`), one is wrong: the
trajectories are refined on registration's offsets too, and the clocks that predict each video's rays better from
the other videos' alone (`reconstruct.heldout`) are kept. Not by the in-sample residual: a wrong clock can move a
video out of the others' time span, where its rays are met alone, or bend the trajectories through them (measured on
the Pose2Sim lab and a synthetic flight, docs/refinement.md). The solve's own clocks stay unless registration's
predict clearly better. Where the solve identified no clock for some videos and kept its seed (whose points sit on
their rays: no residual to compare), registration's offsets are its only clocks and are held to the checks the
solve's own clocks meet (`clock_fit`).
The same where the solve found every clock but its own checks judged them too ambiguous to refine on (the seed
kept), and registration's offsets, found independently from the epipolar geometry, agree with them.
Offsets the user declared (`clock_declared`: --synchronized, --offsets) are exact where the declaration is true:
where the solve's refined clocks agree with them, they are tried too and kept unless the solve's clocks predict
clearly better (the burden reversed).
report.json `temporal.registered_offsets` gives the measures and the choice.
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import replace
from typing import Any

import numpy as np

from dynrecon.jsonvalues import finite_or_none
from reconstruct.clocks.model import Clocks
from reconstruct.clocks.registered import all_declared, offsets_source
from reconstruct.clocks.search import SearchOptions
from reconstruct.free_times import reprojection_px
from reconstruct.heldout import heldout_px, holds_out
from reconstruct.solver.alternation import SolveResult
from reconstruct.solver.problem import Problem
from reconstruct.temporal import Temporal, refine_on_clocks
from reconstruct.time_checks import Check, RefinementJudge, given_offsets_check, rate_unknown
from reconstruct.tracks_path import start_points
from reconstruct.trajectory import RefineOptions, predicted_pair
from sfm.cameras import CameraSet

log = logging.getLogger(__name__)

BETTER = 0.8  # registration's clocks are kept when their median held-out error is below this x the solve's
PATH = "registered_offsets"  # report.json temporal.path when they are kept


def registered_clocks(problem: Problem, cameras: CameraSet, clocks: Clocks) -> Clocks | None:
    """`clocks` with every video's offset taken from cameras.json (`clock_offset`, rate 1 on its own times), in the
    clocks' gauge (their reference video keeps its times); None unless every video has a registered offset."""
    registered = {v.name: v.clock_offset for v in cameras.videos}
    offsets = [registered.get(name) for name in problem.video_names]
    if any(o is None or not math.isfinite(o) for o in offsets):
        return None
    reference = float(registered[clocks.reference])  # type: ignore[arg-type]
    # declared offsets are exact as declared; registration's estimates carry no uncertainty of their own here
    std = 0.0 if all_declared(cameras) else math.nan
    out = copy.deepcopy(clocks)
    for v, offset in enumerate(offsets):
        own = problem.video_index == v
        shift = float(offset) - reference  # type: ignore[arg-type]
        out.global_time[own] = clocks.own_time[own] + shift
        out.global_std[own] = 0.0
        report = out.videos[v]
        report.offset, report.rate, report.drift = shift, 1.0, 0.0
        report.offset_std = report.estimate_std = 0.0 if v == problem.video_names.index(clocks.reference) else std
        report.method, report.identified = "registered", True
    return out


def prefer_registered_offsets(
    problem: Problem,
    cameras: CameraSet,
    seed: SolveResult,
    temporal: Temporal,
    check: dict[str, Any] | None,
    options: RefineOptions,
    search: SearchOptions | None = None,
) -> Temporal:
    """`temporal`, or the trajectories refined on registration's offsets: where the solve's clocks disagree with them
    (`check`: `check_registered_clocks` of `temporal.clocks`) and registration's predict each video's rays from
    the other videos' clearly better (`heldout_px`); or where the solve kept its seed, having left some clock
    unidentified or found every clock but judged them too ambiguous while registration's agree with them, and
    registration's are not refuted by the tracks (`given_offsets`, with `search`) and pass the clock checks
    (`clock_fit`)."""
    unidentified = [c.name for c in temporal.clocks.videos if not c.identified]
    disagree = check is not None and not check.get("agree", True)
    # the solve's clocks, which its own checks found too ambiguous to use, and registration's agree
    confirmed = check is not None and bool(check.get("agree")) and not unidentified
    registered = any(v.clock_offset is not None for v in cameras.videos)
    # a free-times refinement (also "unidentified") fits its rays better than any clock: nothing to try there
    seed_only = (bool(unidentified) or confirmed) and registered and not temporal.refined
    # declared offsets (a trigger, a timecode) the solve's refined clocks agree with: exact where true, an estimate
    # is not (a real triggered rig's recovered clock was off within the agreement's tolerance: docs/refinement.md)
    declared = confirmed and temporal.refined and all_declared(cameras)
    if not disagree and not seed_only and not declared:
        return temporal
    source = offsets_source(cameras)
    clocks = registered_clocks(problem, cameras, temporal.clocks)
    if clocks is None:
        temporal.report[PATH] = {"tried": False, "reason": "some videos have no registered clock offset"}
        return temporal
    # first, the tracks must not clearly prefer other offsets (clocks/given.py); where the held-out comparison judges
    # next, a pair that no other pair with its videos agrees with is left to it
    given, verdicts = given_offsets_check(problem, clocks, search or SearchOptions(), corroboration=not seed_only)
    if not given.passed:
        log.warning("%s were not used: %s", source, given.sentence())
        temporal.report[PATH] = {
            "tried": True,
            "criterion": "given_offsets",
            "checks": [given.to_json()],
            "given_offsets": [v.to_json() for v in verdicts],
            "kept": "solve",
        }
        return temporal
    start = seed.points if seed.stages else start_points(problem, clocks.global_time)
    on_clocks = refine_on_clocks(problem, start, clocks, clocks.model, options)
    points = np.where(np.isfinite(on_clocks.result.points), on_clocks.result.points, start)
    residual = {"solve": _median_px(problem, temporal.points), "registered": _median_px(problem, points)}
    # reported, not judged: see the module's docstring
    predicted = predicted_pair(temporal.trajectories, on_clocks.result) if temporal.trajectories else None
    entry: dict[str, Any] = {
        "tried": True,
        "criterion": "heldout_px",
        "residual_px": {k: finite_or_none(v) for k, v in residual.items()},
        "predicted_px": {
            "solve": finite_or_none(predicted[0] if predicted else None),
            "registered": finite_or_none(predicted[1] if predicted else None),
        },
        "limit": BETTER,
        "declared": all_declared(cameras),
        "given_offsets": given.to_json(),  # passed; its meaning names any refuting pair set aside uncorroborated
    }
    checks: list[Check] = []
    verdict = ""
    if not seed_only:
        theirs, mine, verdict = _compared(problem, temporal, on_clocks.clocks.global_time, options, residual, entry)
        # disagreeing offsets must predict clearly better to replace the solve's clocks; declared ones that agree
        # are kept unless the solve's clocks predict clearly better; what cannot be compared keeps the solve's
        comparable = not (math.isnan(theirs) or math.isnan(mine))  # inf: no shared time under those clocks
        kept = comparable and (not (mine < BETTER * theirs) if declared else theirs < BETTER * mine)
    else:
        # The seed's points sit on their rays (no residual to compare): registration's offsets are the only clocks
        # for the videos the solve could not time, or the independent confirmation of the clocks it found but did
        # not trust; held to the checks the solve's clocks meet (with decoder times clock_fit reports without
        # judging, as for the solve's own clocks).
        checks = RefinementJudge(problem, seed, options).clock_fit(on_clocks.result, rate_unknown(clocks))
        kept = all(c.passed for c in checks)
        entry.update(criterion="clock_fit", checks=[c.to_json() for c in checks], limit=None)
    entry["kept"] = "registered" if kept else "solve"
    if disagree:
        relation = "disagree with"
    elif unidentified:
        relation = f"leave {', '.join(unidentified)} unidentified, unlike"
    elif declared:
        relation = "agree with"
    else:
        relation = "failed the solve's own checks but agree with"
    if checks:
        verdict = "; ".join(f"{c.meaning} {c.value:.3g}, limit {c.limit:.3g}" for c in checks)
    if not kept:
        log.warning(
            "the solve's clocks %s %s, %s (%s): the solve's clocks are kept",
            relation,
            source,
            f"but predict clearly better, under {BETTER:g} x theirs"
            if declared
            else f"which do not predict clearly better, under {BETTER:g} x the solve's"
            if not seed_only
            else "which fail the clock checks",
            verdict,
        )
        temporal.report[PATH] = entry
        return temporal
    (log.info if declared else log.warning)(
        "the solve's clocks %s %s, which %s (%s): refined on them",
        relation,
        source,
        "predict as well" if declared else "do better",
        verdict,
    )
    report = dict(temporal.report)
    report.update(on_clocks.report)
    report.update(
        {
            PATH: entry,
            "path": PATH,
            "refined": True,
            "reason": f"the solve's clocks ({temporal.report.get('path')}) "
            + (
                f"disagreed with {source}"
                if disagree
                else f"left {', '.join(unidentified)} unidentified; {source} identify them"
                if unidentified
                else f"agree with {source}, which predict as well and are exact where the declaration is true"
                if declared
                else f"failed the solve's own checks; {source}, found independently, agree with them"
            ),
        }
    )
    return replace(
        temporal,
        clocks=on_clocks.clocks,
        points=points,
        times=on_clocks.clocks.global_time.copy(),
        refined=True,
        report=report,
        trajectories=on_clocks.result,
    )


def _compared(
    problem: Problem,
    temporal: Temporal,
    registered_times: np.ndarray,
    options: RefineOptions,
    residual: dict[str, float],
    entry: dict[str, Any],
) -> tuple[float, float, str]:
    """How well registration's clocks (`registered_times`) and the solve's predict each video's rays from the other
    videos' (`heldout_px`, median px: theirs, the solve's), with the sentence that says so; `entry` gets the
    measures. Where some frame of the solve's answer has no time, or fewer than three videos see the points, there
    is no held-out fit: the in-sample residual is compared."""
    if np.isfinite(temporal.times).all() and holds_out(problem):
        held = {
            "solve": heldout_px(problem, temporal.times, options),
            "registered": heldout_px(problem, registered_times, options),
        }
        mine, theirs = held["solve"].median_px, held["registered"].median_px
        entry["heldout_px"] = {k: finite_or_none(h.median_px) for k, h in held.items()}
        entry["heldout_per_video_px"] = {
            name: {k: finite_or_none(float(h.per_video_px[v])) for k, h in held.items()}
            for v, name in enumerate(problem.video_names)
        }
        if math.isfinite(mine) and math.isfinite(theirs):
            sentence = (
                f"each video's rays predicted from the others' to {theirs:.3g} px against the solve's {mine:.3g} px"
            )
            return theirs, mine, sentence
        # clocks under which no video's rays can be predicted from the others' put the videos apart in time, where
        # each is fitted alone (offsets typed in milliseconds): they lose to clocks that can, whatever the residual
        if math.isfinite(mine) or math.isfinite(theirs):
            apart = "cameras.json's" if math.isfinite(mine) else "the solve's"
            sentence = f"under {apart} clocks no video's rays can be predicted from the others' (no shared time)"
            return (math.inf, mine, sentence) if math.isfinite(mine) else (theirs, math.inf, sentence)
    mine, theirs = residual["solve"], residual["registered"]
    entry["criterion"] = "residual_px"
    return theirs, mine, f"median residual {theirs:.3g} px against the solve's {mine:.3g} px"


def _median_px(problem: Problem, points: np.ndarray) -> float:
    residual = reprojection_px(problem, points)
    finite = residual[np.isfinite(residual)]
    return float(np.median(finite)) if finite.size else math.nan
