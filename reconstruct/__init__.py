"""Sync-free 3D reconstruction: the self-expressive solver of Zheng et al. (PAMI / ICCV 2015), then the video
clocks and trajectory refinement on them, and how far to trust each point.

    import reconstruct
    result = reconstruct.solve("cameras.json", "tracks.csv")     # or a CameraSet and Tracks already loaded
    result.points.xyz                                            # (F, P, 3), NaN = not reconstructed
    result.write("out")                                          # points3d.csv, sequencing.json, report.json, .rrd

Options: `SolveOptions(solver=SolverOptions(...), temporal=TemporalOptions(...), trust=TrustOptions(...),
recording=RecordingOptions(...) or None)`. Owns `points3d.csv` and `sequencing.json` (`read_points`,
`read_sequencing`). The names below are imported on first use, so that `import reconstruct` stays cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from dynrecon.lazy import lazy_exports

# name -> the module that defines it
_HOMES = {
    "solve": "reconstruct.stage",
    "run": "reconstruct.stage",
    "Reconstruction": "reconstruct.stage",
    "SolveOptions": "reconstruct.stage",
    "SolverOptions": "reconstruct.solver.alternation",
    "WStepOptions": "reconstruct.solver.wstep_options",
    "CandidateOptions": "reconstruct.solver.candidates",
    "RayConstraint": "reconstruct.solver.xstep",
    "TemporalOptions": "reconstruct.temporal",
    "TrustOptions": "reconstruct.trust",
    "TrustPreset": "reconstruct.trust",
    "preset_options": "reconstruct.trust",
    "RecordingOptions": "reconstruct.outputs.recording_options",
    "WorldAxes": "reconstruct.outputs.recording_options",
    "FramePoints": "reconstruct.outputs.points",
    "Sequencing": "reconstruct.outputs.points",
    "read_points": "reconstruct.outputs.points",
    "write_points": "reconstruct.outputs.points",
    "read_sequencing": "reconstruct.outputs.points",
}

__all__ = [
    "CandidateOptions",
    "FramePoints",
    "RayConstraint",
    "Reconstruction",
    "RecordingOptions",
    "Sequencing",
    "SolveOptions",
    "SolverOptions",
    "TemporalOptions",
    "TrustOptions",
    "TrustPreset",
    "WStepOptions",
    "WorldAxes",
    "preset_options",
    "read_points",
    "read_sequencing",
    "run",
    "solve",
    "write_points",
]


__getattr__, __dir__ = lazy_exports(__name__, {name: (home, name) for name, home in _HOMES.items()})


if TYPE_CHECKING:
    from reconstruct.outputs.points import FramePoints, Sequencing, read_points, read_sequencing, write_points
    from reconstruct.outputs.recording_options import RecordingOptions, WorldAxes
    from reconstruct.solver.alternation import SolverOptions
    from reconstruct.solver.candidates import CandidateOptions
    from reconstruct.solver.wstep_options import WStepOptions
    from reconstruct.solver.xstep import RayConstraint
    from reconstruct.stage import Reconstruction, SolveOptions, run, solve
    from reconstruct.temporal import TemporalOptions
    from reconstruct.trust import TrustOptions, TrustPreset, preset_options
