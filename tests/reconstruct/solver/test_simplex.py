import numpy as np
import pytest

from reconstruct.solver.simplex import project_rows_to_simplex


def _reference_projection(v, allowed):
    """Projection by sorting all allowed values (the textbook algorithm, one row at a time)."""
    out = np.zeros_like(v)
    values = v[allowed]
    u = np.sort(values)[::-1]
    css = np.cumsum(u)
    k = max(i for i in range(1, len(u) + 1) if u[i - 1] - (css[i - 1] - 1) / i > 0)
    theta = (css[k - 1] - 1) / k
    out[allowed] = np.maximum(values - theta, 0)
    return out


def test_projection_matches_reference_and_is_on_the_simplex():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(200, 9)) * rng.uniform(0.01, 10, size=(200, 1))
    allowed = rng.random((200, 9)) < 0.7
    allowed[np.arange(200), rng.integers(0, 9, 200)] = True
    projected = project_rows_to_simplex(v, allowed)
    for i in range(200):
        np.testing.assert_allclose(projected[i], _reference_projection(v[i], allowed[i]), atol=1e-12)
    assert np.all(projected >= 0)
    assert np.all(projected[~allowed] == 0)
    np.testing.assert_allclose(projected.sum(axis=1), 1.0)


def test_projection_is_optimal_against_random_feasible_points():
    rng = np.random.default_rng(4)
    v = rng.normal(size=(1, 6))
    p = project_rows_to_simplex(v)[0]
    for _ in range(500):
        q = rng.dirichlet(np.ones(6))
        assert np.sum((v[0] - p) ** 2) <= np.sum((v[0] - q) ** 2) + 1e-12


@pytest.mark.parametrize("row", [[5.0, 5.0, 5.0], [0.0, 0.0, 0.0], [-3.0, 1.0, 2.0]])
def test_projection_edge_cases(row):
    projected = project_rows_to_simplex(np.array([row]))
    assert projected.sum() == pytest.approx(1.0)
    assert np.all(projected >= 0)
