"""The triangle quadrature rules of the surface contact (`fe.surface_quadrature`) against exact integrals of
monomials over the reference triangle: (1/A) int u^a v^b dA = 2 a! b! / (a + b + 2)!."""

from math import factorial

import numpy as np
import pytest

from fe.surface_quadrature import rule

DEGREES = {"centroid": 1, "dunavant-3": 2, "dunavant-6": 4, "dunavant-7": 5, "split-1": 1, "split-4": 1}
"""Polynomial degree each rule integrates exactly (a split rule: the midpoint rule on each piece)."""


def _mean(a: int, b: int) -> float:
    return 2.0 * factorial(a) * factorial(b) / factorial(a + b + 2)


@pytest.mark.parametrize(("name", "degree"), DEGREES.items())
def test_rules_integrate_polynomials_of_their_degree_exactly(name: str, degree: int) -> None:
    points = rule(name)
    assert np.allclose(points[:, :3].sum(axis=1), 1.0) and np.all(points[:, :3] >= 0.0)
    assert points[:, 3].sum() == pytest.approx(1.0, abs=1e-12)
    u, v, w = points[:, 1], points[:, 2], points[:, 3]
    for a in range(degree + 1):
        for b in range(degree + 1 - a):
            assert (w * u**a * v**b).sum() == pytest.approx(_mean(a, b), rel=1e-9, abs=1e-12), (a, b)


def test_split_rules_converge_on_a_kinked_integrand() -> None:
    """The contact law's kind of integrand, max(0, u - 0.3)^2 (a C1 kink across the triangle): the error of
    the split-k rule falls as k^-2."""
    exact = 2.0 * 0.7**4 / 12.0  # (1/A) int (u - c)_+^2 dA with the triangle's width 1 - u in v
    errors = []
    for k in (2, 4, 8):
        points = rule(f"split-{k}")
        errors.append(abs((points[:, 3] * np.maximum(points[:, 1] - 0.3, 0.0) ** 2).sum() - exact))
    assert errors[1] < errors[0] / 3.0 and errors[2] < errors[1] / 3.0, errors


def test_an_unknown_rule_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown surface quadrature rule"):
        rule("gauss-99")
