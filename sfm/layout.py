"""Where `register` keeps its files in WS (the register folder): one place for the paths that the serial stage and
the per-video tasks of `dynrecon batch` both use (docs/formats.md)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dynrecon.readers import check_video_name


@dataclass(frozen=True)
class Layout:
    out: Path  # the register folder: cameras.json, background.ply, register_report.json, frames/, sfm/

    @property
    def previous_dir(self) -> Path:
        """The last successful run's cameras.json, background.ply and register_report.json while a new run has not
        yet replaced them (kept there when it fails)."""
        return self.out / "previous"

    @property
    def frames_dir(self) -> Path:
        return self.out / "frames"

    @property
    def sfm_dir(self) -> Path:
        return self.out / "sfm"

    @property
    def colmap_log(self) -> Path:
        return self.sfm_dir / "colmap.log"

    @property
    def database(self) -> Path:
        """The merged feature database that matching and mapping use."""
        return self.sfm_dir / "database.db"

    @property
    def mask_dir(self) -> Path:
        return self.sfm_dir / "masks"

    @property
    def model_dir(self) -> Path:
        return self.sfm_dir / "models"

    @property
    def mapping(self) -> Path:
        """The capture's matching and mapping outcome: the kept model's name, warnings, seconds."""
        return self.sfm_dir / "mapping.json"

    def features(self, video: str) -> Path:
        """One video's SIFT features (COLMAP's database has one writer: one file per video, merged later)."""
        return self.sfm_dir / "features" / f"{check_video_name(video)}.db"

    def video_dir(self, video: str) -> Path:
        return self.sfm_dir / "videos" / check_video_name(video)

    def plan(self, video: str) -> Path:
        return self.video_dir(video) / "plan.json"

    def extraction(self, video: str) -> Path:
        return self.video_dir(video) / "extract.json"

    def poses(self, video: str) -> Path:
        return self.video_dir(video) / "poses.json"

    def localize_db(self, video: str) -> Path:
        return self.video_dir(video) / "localize.db"

    def video_log(self, video: str) -> Path:
        """COLMAP's log of one video's steps (concurrent tasks never share a log file)."""
        return self.video_dir(video) / "colmap.log"
