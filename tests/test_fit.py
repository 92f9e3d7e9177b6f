"""The fit + intervals core (twin/analysis/fit.py) against independent truth: the normal equations of a
linear model (its solution and covariance, with and without a Gaussian prior), Rosenbrock's known minimum,
the constrained optimum of orthogonal columns with one bound active, and refused input."""

import numpy as np
import pytest
from scipy.optimize import minimize

from twin.analysis.fit import (
    GaussNewtonHooks,
    GaussNewtonSettings,
    Parameters,
    Prior,
    _step,
    gauss_newton,
    linear_step,
    polish,
    predictive_whitened,
    uncertainty,
)

WIDE = 1e9


def _parameters(values, lower=None, upper=None, scale=None) -> Parameters:
    values = np.asarray(values, dtype=float)
    return Parameters(
        tuple(f"p{i}" for i in range(len(values))),
        values,
        np.full(len(values), -WIDE) if lower is None else np.asarray(lower, dtype=float),
        np.full(len(values), WIDE) if upper is None else np.asarray(upper, dtype=float),
        np.ones(len(values)) if scale is None else np.asarray(scale, dtype=float),
    )


def _linear_problem(seed: int = 0, n: int = 300):
    """y = A x_true + noise with columns of very different units (the scales make them alike)."""
    rng = np.random.default_rng(seed)
    units = np.array([1e-3, 1e5, 1.0])
    a = rng.normal(size=(n, 3)) / units
    x_true = np.array([2e-3, -3e5, 0.7])
    y = a @ x_true + rng.normal(scale=0.05, size=n)
    return a, y, units


def test_a_linear_fit_reaches_the_normal_equations_and_their_covariance() -> None:
    a, y, units = _linear_problem()
    start = _parameters(np.zeros(3), scale=units)
    fit = gauss_newton(
        lambda p: y - a @ p.values,
        start,
        GaussNewtonHooks(),
        GaussNewtonSettings(iterations=3, whitened=False),
        start_jacobian=a,
    )
    solution = np.linalg.solve(a.T @ a, a.T @ y)
    r = y - a @ solution
    covariance = r @ r / (len(y) - 3) * np.linalg.inv(a.T @ a)
    assert fit.values == pytest.approx(solution, rel=1e-8)
    assert fit.uncertainty.variance == "residual"
    assert fit.uncertainty.covariance == pytest.approx(covariance, rel=1e-6)
    assert fit.uncertainty.std == pytest.approx(np.sqrt(np.diag(covariance)), rel=1e-8)
    d = np.sqrt(np.diag(covariance))
    assert fit.uncertainty.correlation == pytest.approx(covariance / np.outer(d, d), abs=1e-9)
    intervals = fit.uncertainty.intervals(fit.values)
    assert intervals[:, 1] - intervals[:, 0] == pytest.approx(2 * 1.96 * d, rel=1e-8)
    assert fit.at_bound == () and fit.evaluations >= 1


def test_a_whitened_fit_with_a_prior_matches_the_gaussian_posterior() -> None:
    a, y, units = _linear_problem(seed=1, n=40)
    sigma = 0.05
    prior = Prior(np.array([1e-3, -1e5, 0.0]), np.array([2e-3, 1e5, 0.5]))
    aw, yw = a / sigma, y / sigma
    fit = gauss_newton(
        lambda p: yw - aw @ p.values,
        _parameters(prior.mean, scale=units),
        GaussNewtonHooks(),
        GaussNewtonSettings(iterations=3),
        prior=prior,
        start_jacobian=aw,
    )
    precision = aw.T @ aw + np.diag(1.0 / prior.sigma**2)
    posterior_mean = np.linalg.solve(precision, aw.T @ yw + prior.mean / prior.sigma**2)
    assert fit.values == pytest.approx(posterior_mean, rel=1e-7)
    assert fit.uncertainty.variance == "unit"
    assert fit.uncertainty.covariance == pytest.approx(np.linalg.inv(precision), rel=1e-6)
    expected_cost = np.sum((yw - aw @ posterior_mean) ** 2) + prior.cost(posterior_mean)
    assert fit.cost == pytest.approx(expected_cost, rel=1e-9)


def test_the_uncertainty_condition_is_that_of_the_scaled_normal_matrix() -> None:
    jac = np.diag([1.0, 1e-3]) @ np.eye(2)
    jac = np.vstack([jac, [np.nan, 1.0]])  # a row the model did not reach is left out
    spread = uncertainty(jac, np.array([1.0, 10.0]))
    assert spread.condition == pytest.approx(1e4)  # scaled columns 1 and 1e-2
    assert spread.std == pytest.approx([1.0, 1000.0])  # 1 / |column|, whatever the scale


def test_gauss_newton_finds_rosenbrocks_minimum() -> None:
    def prediction(p: Parameters) -> np.ndarray:
        x0, x1 = p.values
        return np.array([10.0 * (x1 - x0**2), 1.0 - x0])

    def jacobian(p: Parameters) -> np.ndarray:
        return np.array([[-20.0 * p.values[0], 10.0], [-1.0, 0.0]])

    start = _parameters([-1.2, 1.0], lower=[-2.0, -2.0], upper=[2.0, 2.0])
    # From the classic start the full step overshoots the curved valley: it takes four halvings to descend.
    settings = GaussNewtonSettings(iterations=100, backtracks=10)
    fit = gauss_newton(lambda p: -prediction(p), start, GaussNewtonHooks(jacobian=jacobian), settings)
    assert fit.values == pytest.approx([1.0, 1.0], abs=1e-8)
    assert fit.cost == pytest.approx(0.0, abs=1e-14)


def test_a_parameter_pinned_at_its_bound_is_flagged_and_the_other_is_free() -> None:
    # Orthogonal columns: the bounded optimum is the unbounded one with the first value clipped.
    a = np.zeros((4, 2))
    a[:2, 0] = 1.0
    a[2:, 1] = 1.0
    y = np.array([5.0, 5.0, -0.3, -0.1])
    start = _parameters([0.0, 0.0], lower=[-1.0, -1.0], upper=[1.0, 1.0])
    step = linear_step(a, y, start)
    assert step == pytest.approx([1.0, -0.2])
    fit = gauss_newton(lambda p: y - a @ p.values, start, GaussNewtonHooks(), start_jacobian=a)
    assert fit.values == pytest.approx([1.0, -0.2])
    assert fit.at_bound == ("p0",)


def test_a_step_that_does_not_lower_the_cost_is_not_taken() -> None:
    # The given Jacobian points the wrong way: every halved step raises the cost, so the start is kept.
    y = np.array([1.0, 2.0])
    fit = gauss_newton(
        lambda p: y - p.values[0] * np.ones(2), _parameters([0.0]), GaussNewtonHooks(), start_jacobian=-np.ones((2, 1))
    )
    assert fit.values == pytest.approx([0.0]) and fit.jacobian is None and fit.uncertainty is None
    assert fit.evaluations == 1 + 1 + GaussNewtonSettings().backtracks


def test_polish_finds_a_bounded_minimum_and_keeps_a_better_start() -> None:
    one = polish(lambda x: float((x[0] - 0.3) ** 2), _parameters([0.0], [-1.0], [1.0], [0.1]))
    assert one.values == pytest.approx([0.3], abs=1e-4)
    two = polish(lambda x: float(np.sum((x - [0.2, -0.4]) ** 2)), _parameters([0.0, 0.0], [-1, -0.3], [1, 1]))
    assert two.values == pytest.approx([0.2, -0.3], abs=1e-3) and two.at_bound == ("p1",)
    flat = polish(lambda x: 0.0 if x[0] == 0.5 else 1.0, _parameters([0.5], [0.0], [1.0], [0.1]))
    assert flat.values == pytest.approx([0.5]) and flat.cost == 0.0


def test_polish_of_one_parameter_finds_the_deepest_of_several_dips() -> None:
    """A cost with dips every 0.1 about its minimum at 0.67 (as a delay's against a sampled signal): Brent's
    bounded search alone over [0, 1] settles in the dip at 0.47 (measured with scipy); the scan first finds
    the deepest."""

    def cost(x: np.ndarray) -> float:
        return float(0.2 * abs(x[0] - 0.67) + 0.05 * (1.0 - np.cos(2.0 * np.pi * (x[0] - 0.67) / 0.1)))

    fit = polish(cost, _parameters([0.0], [0.0], [1.0], [0.2]))
    assert fit.values == pytest.approx([0.67], abs=1e-3) and fit.cost < 1e-3


@pytest.mark.parametrize(
    "make",
    [
        lambda: Parameters(("a", "b"), np.zeros(1), np.zeros(2), np.ones(2), np.ones(2)),
        lambda: Parameters(("a",), np.zeros(1), np.ones(1), np.zeros(1), np.ones(1)),
        lambda: Parameters(("a",), np.zeros(1), -np.ones(1), np.ones(1), np.zeros(1)),
        lambda: Parameters(("a",), np.full(1, 2.0), -np.ones(1), np.ones(1), np.ones(1)),
        lambda: Parameters(("a",), np.full(1, np.nan), -np.ones(1), np.ones(1), np.ones(1)),
        lambda: uncertainty(np.ones((3, 2)), np.ones(3)),
        lambda: gauss_newton(lambda p: np.zeros(2), _parameters([0.0]), GaussNewtonHooks()),
    ],
)
def test_bad_input_is_refused_with_one_line(make) -> None:
    with pytest.raises(ValueError) as error:
        make()
    assert "\n" not in str(error.value) and str(error.value)


@pytest.mark.parametrize(("overstated", "steps"), [(2.0, 5), (20.0, 2)])
def test_extra_iterations_go_on_while_the_cost_falls_fast(overstated: float, steps: int) -> None:
    """A chord iteration with a Jacobian `overstated` times too steep takes 1/overstated of the way each step: its
    cost falls by 75 % a step (2x) or by 9.75 % (20x, under `extra_if_drop`'s tenth): the first goes on past
    `iterations` to its `extra_iterations`, the second stops at `iterations`."""
    a, y, units = _linear_problem(seed=2)
    settings = GaussNewtonSettings(iterations=2, extra_iterations=3, whitened=False)
    fit = gauss_newton(
        lambda p: y - a @ p.values,
        _parameters(np.zeros(3), scale=units),
        GaussNewtonHooks(),
        settings,
        start_jacobian=overstated * a,
    )
    assert fit.evaluations == 1 + steps
    solution = np.linalg.solve(a.T @ a, a.T @ y)
    assert np.abs(fit.values - solution) == pytest.approx(
        np.abs(solution) * (1.0 - 1.0 / overstated) ** steps, rel=1e-6
    )


def test_a_step_its_hook_finds_unpromising_is_not_taken() -> None:
    """A linear model whose best fit leaves a residual of RMS ~0.05 (the noise): a hook that asks for a predicted RMS
    below 0.01 refuses the first step (the fit stays at its start, one evaluation), one that asks for 0.1 lets the
    fit reach the normal equations' solution; the hook is shown the start's residual and the linear step's."""
    a, y, units = _linear_problem(seed=3)
    solution = np.linalg.solve(a.T @ a, a.T @ y)
    start = _parameters(np.zeros(3), scale=units)
    settings = GaussNewtonSettings(iterations=3, whitened=False)
    shown = []

    def fit_asking_below(limit: float):
        def promising(residual: np.ndarray, predicted: np.ndarray) -> bool:
            shown.append((residual, predicted))
            return float(np.sqrt(np.mean(predicted**2))) < limit

        hooks = GaussNewtonHooks(promising=promising)
        return gauss_newton(lambda p: y - a @ p.values, start, hooks, settings, start_jacobian=a)

    refused = fit_asking_below(0.01)
    assert refused.values == pytest.approx(np.zeros(3)) and refused.evaluations == 1 and refused.jacobian is None
    assert shown[0][0] == pytest.approx(y) and shown[0][1] == pytest.approx(y - a @ solution, abs=1e-9)
    taken = fit_asking_below(0.1)
    assert taken.values == pytest.approx(solution, rel=1e-9)


def test_a_held_out_prediction_whitened_by_its_predictive_spread_is_unit_noise() -> None:
    """Bayesian linear regression by simulation: parameters drawn from their Gaussian prior, unit noise, five folds of
    40 rows; two columns nearly collinear except in the first fold (the others barely fix that direction, which the
    first loads). Each fold is predicted by the prior-regularised fit to the other four; whitened by
    `predictive_whitened` with the other folds' posterior precision, its values must be unit normal (mean square 1
    within 2 %, and the 99.9 % quantile of a normal), while the raw predictions' mean square is about twice that: the
    whitening is what makes the check possible, not a loosening of it."""
    rng = np.random.default_rng(7)
    folds, rows, k = 5, 40, 3
    sigma = np.array([1.0, 5.0, 0.5])
    raw, whitened = [], []
    for _ in range(400):
        base, other, apart = rng.standard_normal((3, folds * rows, 1))
        spread = np.where(np.arange(folds * rows)[:, None] < rows, 1.0, 0.02)  # fold 0 alone tells them apart
        jac = np.hstack([base, base + spread * apart, other])
        truth = sigma * rng.standard_normal(k)
        y = jac @ truth + rng.standard_normal(folds * rows)
        for f in range(folds):
            test = np.arange(folds * rows) // rows == f
            prior = Prior(np.zeros(k), sigma)
            step = linear_step(jac[~test], y[~test], _parameters(np.zeros(k)), prior)
            left = y[test] - jac[test] @ step
            precision = jac[~test].T @ jac[~test] + np.diag(1.0 / sigma**2)
            raw.append(left if f == 0 else left[:0])
            whitened.append(predictive_whitened(left, jac[test], precision))
    raw, whitened = np.concatenate(raw), np.concatenate(whitened)
    assert np.mean(whitened**2) == pytest.approx(1.0, abs=0.02)
    assert np.quantile(np.abs(whitened), 0.999) == pytest.approx(3.29, rel=0.1)
    assert np.mean(raw**2) > 1.8, np.mean(raw**2)  # the first fold's, predicted by the others (1.95)


def test_a_damped_step_that_fails_is_solved_again_more_damped() -> None:
    """A curved valley, r = (100 (y - 3 sin x), 10 (x - 1)), with a Gaussian prior (sigma 3 about the start (-2, 0)):
    from the start the Gauss-Newton step overshoots the valley's bend. Levenberg-Marquardt steps (damping 0.01, a step
    that fails solved again four times more damped, up to six tries; eased after one that holds) go on to the minimum
    of the cost, which scipy's Nelder-Mead finds on the same cost (residual plus prior) independently; steps
    bounded to a prior sigma and halved when they fail stop 796 above it (measured), damped ones given three tries
    852 above."""

    def residual(p: Parameters) -> np.ndarray:
        x, y = p.values
        return np.array([100.0 * (y - 3.0 * np.sin(x)), 10.0 * (x - 1.0)])

    def jacobian(p: Parameters) -> np.ndarray:
        return np.array([[300.0 * np.cos(p.values[0]), -100.0], [-10.0, 0.0]])

    start = _parameters([-2.0, 0.0], lower=[-10.0, -10.0], upper=[10.0, 10.0])
    prior = Prior(np.array([-2.0, 0.0]), np.array([3.0, 3.0]))
    settings = GaussNewtonSettings(iterations=30, backtracks=6, damping=1e-2)
    fit = gauss_newton(residual, start, GaussNewtonHooks(jacobian=jacobian), settings, prior)

    def cost(values: np.ndarray) -> float:
        return float(np.sum(residual(_parameters(values)) ** 2)) + float(prior.cost(values))

    best = minimize(cost, np.array([1.0, 2.5]), method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-12})
    assert fit.cost == pytest.approx(best.fun, rel=1e-3), (fit.values, best.x)
    assert fit.values == pytest.approx(best.x, abs=1e-3)


def test_a_damped_step_holds_each_parameter_back_by_what_the_data_see_of_it() -> None:
    """On a linear residual r = b - J x whose two columns differ a thousandfold in size, the step with damping 1
    minimises |b - J d|^2 + sum_i c_i d_i^2, c_i = |J_i|^2 (Marquardt's scaling): with orthogonal columns each
    parameter goes half its Gauss-Newton way (b_i / J_ii / 2), whatever its column's size; a damping in the parameters'
    own units (sum_i d_i^2) would hold back the small column's parameter alone, the large one going its whole way."""
    jac = np.diag([1.0, 1000.0])
    target = np.array([2.0, 3000.0])
    start = _parameters([0.0, 0.0], lower=[-10.0, -10.0], upper=[10.0, 10.0])
    state = (start, target, float(target @ target))
    assert _step(jac, state, start, None, 1.0) == pytest.approx([1.0, 1.5], rel=1e-6)
    assert _step(jac, state, start, None, 0.0) == pytest.approx([2.0, 3.0], rel=1e-6)
