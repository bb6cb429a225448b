"""The subject path's batched two-view fits: one degenerate sample never fails the batch."""

from __future__ import annotations

import numpy as np

from sfm.subject.geometry import eight_point, sampson


def test_a_singular_sample_scores_nothing_and_the_others_are_fitted() -> None:
    """Eight copies of one far point make the sample's 8x8 system singular even with the ridge (which vanishes
    beside its entries): numpy's batched solve raised for the whole batch, a traceback in `register`, depending on
    which samples the draw made. Now that sample gives no hypothesis and the good one is still fitted."""
    rng = np.random.default_rng(0)
    R = np.array([[np.cos(0.3), 0, np.sin(0.3)], [0, 1, 0], [-np.sin(0.3), 0, np.cos(0.3)]])
    t = np.array([1.0, 0.2, 0.1])
    X = rng.uniform(-1, 1, (8, 3)) + np.array([0.0, 0.0, 5.0])
    xa = X[:, :2] / X[:, 2:]
    Xb = X @ R.T + t
    xb = Xb[:, :2] / Xb[:, 2:]
    bad_a, bad_b = np.full((8, 2), 1e6), np.full((8, 2), 2e6)
    F = eight_point(np.stack([xa, bad_a]), np.stack([xb, bad_b]), essential=True)
    assert np.isfinite(F).all()
    assert float(sampson(F[0][None], xa, xb).max()) < 1e-12  # the good sample's exact geometry
