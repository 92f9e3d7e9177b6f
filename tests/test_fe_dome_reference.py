"""The FE dome (membrane only) against the independent axisymmetric reference, converging under refinement."""

import numpy as np
import pytest

from fe.axisymmetric import indent_dome
from fe.dome import run_dome

R, T, MU, RATIO, R_IND = 10e-3, 0.1e-3, 1e5, 1.5, 5e-3  # m, m, Pa, -, m
DEPTHS = np.array([0.0, 1.0e-3, 1.5e-3])  # m past first touch


@pytest.fixture(scope="module")
def reference() -> tuple[np.ndarray, np.ndarray]:
    states = indent_dome(R, T, MU, RATIO, R_IND, list(DEPTHS))
    return np.array([s.pressure for s in states]), np.array([s.force for s in states])


def _fe(max_edge: float) -> tuple[np.ndarray, np.ndarray]:
    result = run_dome(R, T, MU, RATIO, False, R_IND, DEPTHS, max_edge)
    assert all(inc.converged for inc in result.increments)
    return np.array([inc.pressure for inc in result.increments]), np.array([-inc.force[2] for inc in result.increments])


def test_fe_dome_matches_axisymmetric_membrane_theory_and_converges(reference: tuple[np.ndarray, np.ndarray]) -> None:
    p_ref, f_ref = reference
    p_coarse, _ = _fe(R / 6)
    p_fine, f_fine = _fe(R / 12)
    err_coarse, err_fine = np.abs(p_coarse / p_ref - 1), np.abs(p_fine / p_ref - 1)
    assert np.all(err_fine < 0.005), err_fine
    assert np.all(err_fine < err_coarse), (err_coarse, err_fine)
    # The contact force is resolved by a few rings of nodes only: a few % on the finer mesh.
    assert f_fine[0] == 0.0
    assert np.all(np.abs(f_fine[1:] / f_ref[1:] - 1) < 0.05), (f_fine, f_ref)
