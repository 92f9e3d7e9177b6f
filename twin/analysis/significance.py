"""When is a whitened residual noise? The stopping rule: a chi-square test that scales with the data.

Each channel c of the residual (force x, y, z in N; PDC in counts) is divided by its noise sigma_c,
estimated from the data (the MAD of successive-sample differences, `compare.noise_estimate`). For a
model that lacks nothing, the whitened values are unit normal draws, up to the error of the sigma
estimates. With n_c finite values of channel c, n = sum n_c and q nuisance directions projected out
(one constant offset per trajectory and channel, one PDC gain per sensor), the statistic

    R = sum r^2 / nu,   nu = n - q,

has mean 1 and, to first order, variance

    Var R = 2 / nu + sum_c (n_c / n)^2 * V / M_c,

where 2 / nu is the chi-square's own spread and the second term that of the estimated noise variances:
M_c successive differences went into sigma_c. The estimate and the sum of squares come from the same
samples, so V is the MAD estimate's own variance, M Var(sigma_hat^2 / sigma^2) = 6.64 for the MAD of
successive differences of white Gaussian noise, less twice its covariance with the mean square of
those samples: V = 2.51 (both measured by simulation with n = M; tests/test_diagnose_verdict.py checks
the spread of R). The residual is noise at level `ALPHA` when R <= 1 + z_(1 - ALPHA) sqrt(Var R). The
RMS threshold is the square root of that: about 1.2 for a few hundred samples, 1.01 for a campaign of
hundreds of thousands.

The test is applied to held-out residuals (each indenter predicted by a fit made without it), which
carry no fitted effect parameters, so nu loses only the nuisances.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

ALPHA = 1e-3
"""False-alarm probability of the test on a residual that is noise (one-sided)."""
NOISE_ESTIMATE_VARIANCE = 2.51
"""V: M Var(R) - 2 M / n for a variance estimated by the MAD of M successive differences of white
Gaussian noise (1.4826 MAD / sqrt 2) from the samples whose squares R sums (see the module docstring)."""


@dataclass(frozen=True)
class NoiseTest:
    """The chi-square test of a whitened residual: statistic R, its threshold and the RMS threshold."""

    ratio: float  # R = chi2 / nu
    threshold: float  # 1 + z sqrt(Var R)
    dof: float  # nu
    alpha: float

    @property
    def rms_threshold(self) -> float:
        """The whitened RMS a residual may reach and still be noise (sqrt of the ratio threshold)."""
        return float(np.sqrt(self.threshold))

    @property
    def is_noise(self) -> bool:
        """Whether the residual passes (no significant excess over the noise)."""
        return self.ratio <= self.threshold


def ratio_threshold(
    counts: Sequence[int], noise_samples: Sequence[int], nuisances: int, alpha: float = ALPHA
) -> tuple[float, float]:
    """(threshold on R, nu) for channels with `counts` finite whitened values and `noise_samples`
    differences behind each channel's sigma, after `nuisances` projected directions."""
    counts = np.asarray(counts, dtype=float)
    noise_samples = np.asarray(noise_samples, dtype=float)
    if counts.shape != noise_samples.shape or counts.sum() <= nuisances:
        raise ValueError(f"need more values than nuisances: {counts.tolist()} values, {nuisances} nuisances")
    n = counts.sum()
    dof = n - nuisances
    weights = counts / n
    variance = 2.0 / dof + float(np.sum(weights**2 * NOISE_ESTIMATE_VARIANCE / np.maximum(noise_samples, 1.0)))
    return 1.0 + float(norm.isf(alpha)) * float(np.sqrt(variance)), float(dof)


def noise_test(
    squares: Sequence[float],
    counts: Sequence[int],
    noise_samples: Sequence[int],
    nuisances: int,
    alpha: float = ALPHA,
) -> NoiseTest:
    """Test per-channel sums of squared whitened residuals `squares` (with their `counts` of values)."""
    threshold, dof = ratio_threshold(counts, noise_samples, nuisances, alpha)
    return NoiseTest(float(np.sum(squares)) / dof, threshold, dof, alpha)
