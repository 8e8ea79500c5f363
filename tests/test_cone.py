"""Algorithm 5 (cone projection) against a numerical solver and the projection's properties."""

import numpy as np
import pytest
from scipy.optimize import minimize

from physics.cone import Branch, cone_project, cone_weights

DIMS = (2, 3, 5)  # friction dimensions d for MuJoCo condim 3, 4, 6


def random_cone(rng: np.random.Generator, d: int) -> tuple[np.ndarray, float, float]:
    """Friction coefficients μ (d,) and regularizers r_0, r_F as MuJoCo builds them:
    r_F = r_0 μ_1² ⟨μ_j⁻²⟩ / impratio, so that μ̂² = μ_1² / impratio."""
    mu = np.exp(rng.uniform(np.log(1e-3), np.log(2.0), d))
    r0 = float(np.exp(rng.uniform(np.log(1e-4), np.log(1e2))))
    impratio = float(np.exp(rng.uniform(np.log(0.5), np.log(100.0))))
    rF = r0 * mu[0] ** 2 * float(np.mean(mu**-2)) / impratio
    return mu, r0, rF


def in_cone(x: np.ndarray, mu: np.ndarray, tol: float = 1e-9) -> bool:
    scale = max(1.0, float(np.max(np.abs(x / np.concatenate([[1.0], mu])))))
    return x[0] >= -tol * scale and x[0] - np.linalg.norm(x[1:] / mu) >= -tol * scale


def scipy_projection(y: np.ndarray, mu: np.ndarray, r: np.ndarray) -> np.ndarray:
    """min Σ r_k (x_k − y_k)² over the cone, by SLSQP.

    Solved in the coordinates of eq. 16, x̂ = r^½ x, where the cone is circular (eq. 17) and the
    problem well conditioned: min ½‖x̂ − ŷ‖² s.t. μ̂ x̂_0 − ‖x̂_t‖ ≥ 0 (a concave constraint:
    a convex problem). It starts off the cone's axis, where the constraint is smooth.
    """
    sqrt_r = np.sqrt(r)
    mu_hat = mu[0] * np.sqrt(r[1] / r[0])
    yh = sqrt_r * y
    size = np.linalg.norm(yh)
    direction = yh[1:] / max(np.linalg.norm(yh[1:]), 1e-300)
    start = np.concatenate([[size], 0.5 * size * mu_hat * direction])
    xh = minimize(
        lambda xh: 0.5 * np.sum((xh - yh) ** 2),
        x0=start,
        jac=lambda xh: xh - yh,
        constraints=[
            {
                "type": "ineq",
                "fun": lambda xh: mu_hat * xh[0] - np.linalg.norm(xh[1:]),
                "jac": lambda xh: np.concatenate(
                    [[mu_hat], -xh[1:] / max(np.linalg.norm(xh[1:]), 1e-300)]
                ),
            },
        ],
        method="SLSQP",
        options={"ftol": 1e-16, "maxiter": 1000},
    ).x
    return xh / sqrt_r


def weighted_distance2(x: np.ndarray, y: np.ndarray, r: np.ndarray) -> float:
    return float(np.sum(r * (x - y) ** 2))


@pytest.mark.parametrize("d", DIMS)
def test_algorithm5_matches_scipy_on_random_cones(d: int) -> None:
    rng = np.random.default_rng(d)
    worst, compared, trials = 0.0, 0, 500
    for _ in range(trials):
        mu, r0, rF = random_cone(rng, d)
        r, _ = cone_weights(mu, r0, rF)
        y = rng.normal(size=d + 1) * np.exp(rng.uniform(-3, 3))
        x, _ = cone_project(y, mu, r0, rF)
        assert in_cone(x, mu)
        x_ref = scipy_projection(y, mu, r)
        if not in_cone(x_ref, mu):
            continue  # SLSQP stopped outside the cone: no reference for this problem
        compared += 1
        # Algorithm 5 is exact: never farther from y than the iterative solution ...
        dist, dist_ref = weighted_distance2(x, y, r), weighted_distance2(x_ref, y, r)
        assert dist <= dist_ref * (1 + 1e-7) + 1e-15 * weighted_distance2(0 * y, y, r)
        # ... and the same point to the iterative solver's tolerance (scaled coordinates)
        scale = np.linalg.norm(np.sqrt(r) * y)
        worst = max(worst, float(np.linalg.norm(np.sqrt(r) * (x - x_ref)) / scale))
    assert compared >= 0.85 * trials
    assert worst < 1e-5


@pytest.mark.parametrize("d", DIMS)
def test_projection_is_idempotent_feasible_and_optimal(d: int) -> None:
    """Variational inequality of a projection: (y − x)ᵀ R (z − x) ≤ 0 for every z in the cone."""
    rng = np.random.default_rng(10 + d)
    for _ in range(500):
        mu, r0, rF = random_cone(rng, d)
        r, _ = cone_weights(mu, r0, rF)
        y = rng.normal(size=d + 1)
        x, _ = cone_project(y, mu, r0, rF)
        assert in_cone(x, mu)
        x2, _ = cone_project(x, mu, r0, rF)
        np.testing.assert_allclose(x2, x, rtol=1e-9, atol=1e-12)
        # random points of the cone: its generators and a few interior points
        for _ in range(20):
            t = rng.normal(size=d)
            z = np.concatenate([[1.0], mu * t / np.linalg.norm(t) * rng.uniform(0, 1)])
            z *= rng.exponential()
            assert np.dot(r * (y - x), z - x) <= 1e-9 * (1 + np.linalg.norm(y) * np.linalg.norm(z))


def test_branches_inside_surface_tip() -> None:
    mu, r0, rF = np.array([0.5, 0.5]), 1.0, 1.0
    inside = np.array([1.0, 0.1, -0.2])
    x, branch = cone_project(inside, mu, r0, rF)
    assert branch == Branch.STICKING and np.array_equal(x, inside)
    outside = np.array([1.0, 3.0, 0.0])
    x, branch = cone_project(outside, mu, r0, rF)
    assert branch == Branch.SLIDING
    assert x[0] > 0 and np.isclose(x[0], np.linalg.norm(x[1:] / mu))
    polar = np.array([-1.0, 0.1, 0.1])
    x, branch = cone_project(polar, mu, r0, rF)
    assert branch == Branch.SEPARATING and not np.any(x)


@pytest.mark.parametrize("d", DIMS)
def test_special_case_zero_normal_eq20(d: int) -> None:
    """ŷ_0 = 0: the closed form of eq. 20 equals the numerical projection."""
    rng = np.random.default_rng(20 + d)
    for _ in range(100):
        mu, r0, rF = random_cone(rng, d)
        r, _ = cone_weights(mu, r0, rF)
        y = np.concatenate([[0.0], rng.normal(size=d)])
        x, branch = cone_project(y, mu, r0, rF)
        assert branch == Branch.SLIDING
        assert np.isclose(x[0], np.linalg.norm(x[1:] / mu), rtol=1e-9)
        x_ref = scipy_projection(y, mu, r)
        assert weighted_distance2(x, y, r) <= weighted_distance2(x_ref, y, r) * (1 + 1e-7)
        scale = np.linalg.norm(np.sqrt(r) * y)
        assert np.linalg.norm(np.sqrt(r) * (x - x_ref)) <= 1e-5 * scale


@pytest.mark.parametrize("d", DIMS)
def test_special_case_no_friction_component(d: int) -> None:
    """y_j = 0 for all j ≥ 1: the tip when y_0 < 0, y itself when y_0 ≥ 0."""
    mu, r0, rF = np.full(d, 0.7), 2.0, 0.5
    x, branch = cone_project(np.concatenate([[-1.5], np.zeros(d)]), mu, r0, rF)
    assert branch == Branch.SEPARATING and not np.any(x)
    y = np.concatenate([[1.5], np.zeros(d)])
    x, branch = cone_project(y, mu, r0, rF)
    assert branch == Branch.STICKING and np.array_equal(x, y)


def test_weights_satisfy_eq17_and_mean_eq22() -> None:
    rng = np.random.default_rng(3)
    for d in DIMS:
        mu, r0, rF = random_cone(rng, d)
        r, mu_hat2 = cone_weights(mu, r0, rF)
        np.testing.assert_allclose(mu**2 * r[1:], mu_hat2 * r0, rtol=1e-12)  # eq. 17
        assert np.isclose(r[1:].mean(), rF, rtol=1e-12)  # r_F = ⟨r_j⟩
