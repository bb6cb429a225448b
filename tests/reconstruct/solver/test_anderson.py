import numpy as np

from reconstruct.solver.anderson import AndersonMixer


def _contraction(seed: int = 0, n: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x -> A x + b with spectral radius 0.95 (slow for plain iteration), and its fixed point."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    A = Q @ np.diag(np.linspace(0.1, 0.95, n)) @ Q.T
    b = rng.normal(size=n)
    return A, b, np.linalg.solve(np.eye(n) - A, b)


def _iterations_to(tol: float, mixer: AndersonMixer | None, A: np.ndarray, b: np.ndarray, fixed: np.ndarray) -> int:
    x = np.zeros_like(b)
    for k in range(1, 2000):
        g = A @ x + b
        x = mixer.mix(x, g) if mixer is not None else g
        if np.linalg.norm(x - fixed) < tol * np.linalg.norm(fixed):
            return k
    return 2000


def test_anderson_reaches_the_fixed_point_of_a_linear_map_much_faster():
    A, b, fixed = _contraction()
    plain = _iterations_to(1e-8, None, A, b, fixed)
    mixed = _iterations_to(1e-8, AndersonMixer(memory=10), A, b, fixed)
    assert plain > 300
    assert mixed < plain / 5


def test_first_mix_is_the_plain_step_and_reset_forgets_history():
    mixer = AndersonMixer(memory=3)
    x, g = np.zeros((2, 3)), np.ones((2, 3))
    np.testing.assert_array_equal(mixer.mix(x, g), g)
    mixer.mix(g, 1.5 * g)
    mixer.reset()
    np.testing.assert_array_equal(mixer.mix(x, g), g)


def test_degenerate_history_falls_back_to_the_plain_step():
    """Iterates that repeat exactly make the least-squares system singular: the mixer must not return inf/NaN."""
    mixer = AndersonMixer(memory=3)
    x, g = np.zeros(4), np.arange(4.0)
    mixer.mix(x, g)
    out = mixer.mix(x, g)  # same pair again: zero differences
    assert np.all(np.isfinite(out))
    np.testing.assert_array_equal(out, g)
