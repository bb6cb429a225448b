"""The trust measures' batched construction against the plain one."""

import dataclasses

import numpy as np
import scipy.sparse as sp

from reconstruct.trust import _gram_blocks, neighbourhood_condition, neighbourhoods


def _reference_condition(gram, rays, valid=None):
    """The earlier construction: einsum products, (g, h) blocks transposed into the 3n x 3n matrix."""
    B, n = gram.shape[:2]
    valid = np.ones((B, n), dtype=bool) if valid is None else valid
    observed = np.isfinite(rays).all(axis=-1)
    r = np.nan_to_num(rays)
    projector = np.where(observed[..., None, None], r[..., :, None] * r[..., None, :], np.eye(3))
    projector = np.where(valid[..., None, None], projector, 0.0)
    blocks = gram[:, :, :, None, None] * np.einsum("bgij,bhjk->bghik", projector, projector)
    big = blocks.transpose(0, 1, 3, 2, 4).reshape(B, 3 * n, 3 * n)
    c = np.einsum("bii->b", big) + 1.0
    complement = np.zeros((B, n, 3, n, 3))
    idx = np.arange(n)
    complement[:, idx, :, idx, :] = (np.eye(3) - projector).transpose(1, 0, 2, 3)
    big = big + c[:, None, None] * complement.reshape(B, 3 * n, 3 * n)
    smallest = np.linalg.eigvalsh(big)[:, 0]
    return 1.0 / np.maximum(smallest, 1e-13 * c)


def test_condition_matches_the_einsum_construction():
    # rows with every slot in use observed take the n x n form (its own rounding), the others the 3n x 3n one, bit
    # for bit the construction before it
    rng = np.random.default_rng(0)
    for _ in range(60):
        B, n = int(rng.integers(1, 40)), int(rng.integers(1, 6))
        A = rng.normal(size=(B, n, n))
        gram = A @ A.transpose(0, 2, 1) * rng.choice([1e-6, 1.0, 1e6])
        gram[rng.random(gram.shape) < 0.2] = 0.0
        gram[rng.random(gram.shape) < 0.1] *= -1  # negative zeros and signs
        rays = rng.normal(size=(B, n, 3))
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        rays[rng.random((B, n)) < 0.3] = np.nan
        rays[rng.random((B, n, 3)) < 0.1] = 0.0
        rays[rng.random((B, n, 3)) < 0.05] = -0.0
        with np.errstate(invalid="ignore"):  # a ray zeroed whole becomes NaN: unobserved
            rays /= np.linalg.norm(rays, axis=-1, keepdims=True)  # unit, as viewing rays are (zeros stay signed)
        valid = rng.random((B, n)) < 0.8
        for v in (None, valid):
            got, expected = neighbourhood_condition(gram, rays, v), _reference_condition(gram, rays, v)
            in_use = np.ones((B, n), dtype=bool) if v is None else v
            general = ~np.all(np.isfinite(rays).all(axis=-1) | ~in_use, axis=1)
            assert got[general].tobytes() == expected[general].tobytes()
            # the smallest eigenvalue to rounding of the largest (c, the trace + 1)
            c = np.abs(np.einsum("bgg->b", gram)) + 1.0
            assert np.all(np.abs(1.0 / got - 1.0 / expected) <= 1e-9 * c * 3)


def test_gram_blocks_are_the_submatrices_of_the_sparse_gram():
    F = 50
    W = sp.random(F, F, density=0.08, random_state=3, format="csc")
    W.setdiag(0.0)
    W.eliminate_zeros()
    M = (sp.identity(F, format="csc") - W).tocsr()
    G = (M @ M.T).tocsr()
    hood = neighbourhoods(W, 0.02, 4)
    gram = _gram_blocks(G, hood)
    for f in range(F):
        members = hood[f][hood[f] >= 0]
        k = len(members)
        expected = np.zeros((hood.shape[1], hood.shape[1]))
        expected[:k, :k] = G[members][:, members].toarray()
        assert gram[f].tobytes() == expected.tobytes()
    assert _gram_blocks(sp.csr_matrix((F, F)), hood).shape == (F, hood.shape[1], hood.shape[1])


def test_a_written_point_far_from_its_own_ray_is_flagged():
    """The sensitive preset's reprojection test (2026-11-30): refined trajectories that cut a fast motion short (a
    real bat's wing tips: 12 % of the rows over 30 mm flagged before, 53 % now, 2.3 % of all rows flagged) leave
    the written point off its observation's ray; unobserved points have no ray to leave."""
    from reconstruct.trust import TrustPreset, flag_points, flag_rule, preset_options

    F, P = 40, 2
    quiet = np.ones((F, P))
    observed = np.ones((F, P), dtype=bool)
    observed[5, 1] = False
    reprojection = np.full((F, P), 1.0)
    reprojection[3, 0] = 5.5  # over max(5, 5 x median 1)
    reprojection[4, 0] = 4.9  # under it
    reprojection[5, 1] = np.nan  # unobserved
    measures = {
        "residual_px": 0.1 * quiet,
        "bound_px": 0.1 * quiet,
        "sequence_jump": quiet,
        "component": 100 * quiet,
        "smoothness_px": quiet,
        "support": quiet,
        "step_px": quiet,
        "views": 3 * quiet,
        "observed": observed,
        "video_end": np.zeros((F, P), dtype=bool),
        "reprojection_px": reprojection,
    }
    options = preset_options(TrustPreset.SENSITIVE)
    flag, limits = flag_points(options, np.ones((F, P), dtype=bool), measures)
    assert limits["reprojection_px"] == 5.0
    assert flag[3, 0] and not flag[4, 0] and not flag[5, 1] and flag.sum() == 1
    assert "reprojection_px > max(5, 5 x median reprojection_px)" in flag_rule(options)
    off = dataclasses.replace(options, reprojection_px=0.0)
    assert not flag_points(off, np.ones((F, P), dtype=bool), measures)[0].any()
