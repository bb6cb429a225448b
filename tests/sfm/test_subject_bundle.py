"""The subject bundle's analytic Jacobian against finite differences of its residuals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative

from sfm.subject.bundle import _fill_knots
from sfm.subject.bundle_model import Bundle, jacobian, obs_arrays, pack, stacked
from sfm.subject.chain import Knots
from sfm.subject.geometry import rodrigues
from sfm.subject.model import SubjectVideo
from sfm.subject.observations import VideoObs, normalize


def _rig(rng: np.random.Generator, gauge: bool, free_pp: bool, phone: bool) -> tuple[Bundle, list[VideoObs]]:
    """Three cameras around two moving points: the first two with known intrinsics, the first with a held pose."""
    T, F, P = 14, 10, 2
    knots = Knots(t0=0.0, h=0.1, X=rng.normal(0.0, 0.3, (T, P, 3)))
    rvec = np.array([[0.0, 0.0, 0.0], [0.0, 0.6, 0.0], [0.1, -0.5, 0.0]])
    t = np.array([[0.0, 0.0, 4.0], [-2.0, 0.0, 4.5], [2.0, 0.3, 4.2]])
    R = rodrigues(rvec)
    obs = []
    for c in range(3):
        times = 0.05 + 0.11 * np.arange(F)
        video = SubjectVideo(name=f"cam{c}", width=640, height=480, times=times)
        K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
        X = np.stack([np.interp(times, knots.times, knots.X[:, p, d]) for p in range(P) for d in range(3)], -1)
        Xc = X.reshape(F, P, 3) @ R[c].T + t[c]
        xy = Xc[..., :2] / Xc[..., 2:] * 500.0 + K[:2, 2] + rng.normal(0, 0.5, (F, P, 2))
        xy[rng.uniform(size=(F, P)) < 0.1] = np.nan
        obs.append(
            VideoObs(
                name=video.name,
                video=video,
                times=times,
                period=0.11,
                xy=xy,
                norm=normalize(xy, K, None),
                K=K,
                known_K=c < 2,
                dist=None,
            )
        )
    b = Bundle(
        cams=[0, 1, 2],
        rvec=rvec + rng.normal(0, 0.01, (3, 3)),
        t=t,
        focal=np.full(3, 520.0),
        k1=np.full(3, 0.01),
        k2=np.zeros(3),
        pp=np.array([o.video_centre for o in obs]),
        offsets=np.array([0.0, 0.013, -0.027]),  # no observation on a knot, where the slope jumps
        knots=knots,
        fixed_pose={0},
        fixed_offset={0},
        gauge=(1, 2, 4.0) if gauge else None,
        keep=[np.isfinite(o.xy[..., 0]) for o in obs],
        depth=4.0,
        focal_prior=np.full(3, 500.0),
        pp_prior=np.array([o.video_centre for o in obs]) if free_pp else None,
        pp_sigma=10.0,
    )
    if phone:  # the first camera posed frame by frame (a handheld video the background posed): held
        turn = rodrigues(rng.normal(0.0, 0.05, (F, 3)))
        b.frame_poses[0] = (turn @ R[0], t[0] + rng.normal(0.0, 0.05, (F, 3)))
    return b, obs


@pytest.mark.parametrize(
    ("gauge", "free_pp", "phone"),
    [(False, False, False), (True, False, False), (True, True, False), (True, True, True)],
)
def test_the_analytic_jacobian_is_the_derivative_of_the_residuals(gauge: bool, free_pp: bool, phone: bool) -> None:
    b, obs = _rig(np.random.default_rng(3), gauge, free_pp, phone)
    b.knots.X = _fill_knots(b.knots.X)
    arrays = obs_arrays(b, obs)
    x0 = pack(b, obs)

    analytic = jacobian(b, obs, x0, arrays).toarray()
    numeric = approx_derivative(lambda x: stacked(b, obs, x, arrays), x0, method="3-point")
    assert analytic.shape == numeric.shape
    scale = np.abs(numeric).max(axis=0, keepdims=True) + 1e-6  # per parameter: the largest pixels per unit of it
    assert (np.abs(analytic - numeric) / scale).max() < 1e-5
