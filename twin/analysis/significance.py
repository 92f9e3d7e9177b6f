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

The test is applied to held-out residuals (each indenter predicted by a fit made without it). These lose
no degrees of freedom to the fit, but they carry its estimation error: the parameters fitted on the other
folds are off by their own noise, and the left-out prediction extrapolates that error. For a linear fit
of the whitened sensitivity X (rows in folds g; X_g a fold's rows, X_~g the others') to white unit noise,
the held-out residual is r = (I - P) e with P_g,~g = X_g (X_~g^T X_~g)^-1 X_~g^T, so its sum of squares
has mean n + sum_g tr(X_g (X_~g^T X_~g)^-1 X_g^T): for Gaussian noise it is a chi-square of n - m degrees
plus sum_j (1 + e_j) chi2(1), the e_j the m non-zero eigenvalues of (I - P)^T (I - P) - I
(`out_of_fold_excess`). The excess is large where a fold barely excites a direction the left-out fold
loads heavily (the F/T map's lateral columns, fitted on one indenter's small lateral forces: 793 on 20272
values, 3.9 %, three e_j of 220 each, on the hidden-effect tests' campaign, measured before `out_of_fold_excess`
worked on an orthonormal basis; docs/analysis.md). A held-out
residual is therefore noise when R is below the 1 - ALPHA quantile of that sum (over nu, the nuisances
taken from its unit-weight part) plus a normal term of the noise estimates' spread, found by the
Lugannani-Rice saddlepoint tail (`weighted_chi2_quantile`): a few large e_j make the sum skewed, and a
normal tail with the same mean and variance alarms ten times too often at ALPHA = 1e-3
(tests/test_diagnose_verdict.py checks the false-alarm rate against direct leave-one-fold-out fits).
Without an out-of-fold fit the normal rule above is kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.stats import norm

ALPHA = 1e-3
"""False-alarm probability of the test on a residual that is noise (one-sided)."""
NOISE_ESTIMATE_VARIANCE = 2.51
"""V: M Var(R) - 2 M / n for a variance estimated by the MAD of M successive differences of white
Gaussian noise (1.4826 MAD / sqrt 2) from the samples whose squares R sums (see the module docstring)."""


@dataclass(frozen=True)
class OutOfFold:
    """What fits made on other folds add to the held-out sum of squares of white unit noise (see the module
    docstring): that sum is a chi-square with nu - len(excess) degrees of freedom plus 1 + e times a chi-square
    of one degree for each e of `excess` (the non-zero eigenvalues of (I - P)^T (I - P) - I)."""

    excess: tuple[float, ...] = ()

    @property
    def mean(self) -> float:
        """The expected excess of the sum of squares over nu."""
        return float(np.sum(self.excess))

    @property
    def variance(self) -> float:
        """The variance of the sum of squares beyond the noise's own 2 nu."""
        e = np.asarray(self.excess)
        return float(4.0 * np.sum(e) + 2.0 * np.sum(e**2))


NO_FIT = OutOfFold()
"""A residual no out-of-fold fit went into (the test as for the base residual)."""


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
    counts: Sequence[int],
    noise_samples: Sequence[int],
    nuisances: int,
    alpha: float = ALPHA,
    out_of_fold: OutOfFold = NO_FIT,
) -> tuple[float, float]:
    """(threshold on R, nu) for channels with `counts` finite whitened values and `noise_samples`
    differences behind each channel's sigma, after `nuisances` projected directions; for a held-out
    residual, `out_of_fold` is what the fits on the other folds add (`out_of_fold_excess`)."""
    counts = np.asarray(counts, dtype=float)
    noise_samples = np.asarray(noise_samples, dtype=float)
    if counts.shape != noise_samples.shape or counts.sum() <= nuisances:
        raise ValueError(f"need more values than nuisances: {counts.tolist()} values, {nuisances} nuisances")
    n = counts.sum()
    dof = n - nuisances
    weights = counts / n
    variance = 2.0 / dof + float(np.sum(weights**2 * NOISE_ESTIMATE_VARIANCE / np.maximum(noise_samples, 1.0)))
    if not out_of_fold.excess:
        return 1.0 + float(norm.isf(alpha)) * float(np.sqrt(variance)), float(dof)
    weights = np.r_[1.0, 1.0 + np.asarray(out_of_fold.excess)]
    degrees = np.r_[dof - len(out_of_fold.excess), np.ones(len(out_of_fold.excess))]
    estimate_variance = (variance - 2.0 / dof) * dof**2  # the noise estimate's share, in units of the sum
    return weighted_chi2_quantile(weights, degrees, estimate_variance, alpha) / dof, float(dof)


def weighted_chi2_quantile(weights: np.ndarray, degrees: np.ndarray, normal_variance: float, alpha: float) -> float:
    """x with P(S > x) = alpha for S = sum_j weights_j chi2(degrees_j) + N(0, normal_variance), independent
    terms: the Lugannani-Rice saddlepoint tail (relative error of a few per cent in the tail probability for
    such sums), solved for x."""
    weights, degrees = np.asarray(weights, dtype=float), np.asarray(degrees, dtype=float)
    keep = (weights > 0) & (degrees > 0)
    weights, degrees = weights[keep], degrees[keep]
    mean = float(weights @ degrees)
    sd = float(np.sqrt(2.0 * (weights**2) @ degrees + normal_variance))
    ceiling = 0.5 / weights.max()  # the cumulant generating function ends at t = 1 / (2 max weight)

    def cumulants(t: float) -> tuple[float, float, float]:
        """K(t), K'(t), K''(t) of S."""
        d = 1.0 - 2.0 * weights * t
        k0 = -0.5 * degrees @ np.log(d) + 0.5 * normal_variance * t**2
        k1 = degrees @ (weights / d) + normal_variance * t
        k2 = degrees @ (2.0 * weights**2 / d**2) + normal_variance
        return float(k0), float(k1), float(k2)

    def tail(x: float) -> float:
        t = brentq(lambda u: cumulants(u)[1] - x, 0.0, ceiling * (1.0 - 1e-12))
        k0, _, k2 = cumulants(t)
        w = np.sqrt(2.0 * (t * x - k0))
        v = t * np.sqrt(k2)
        return float(norm.sf(w) + norm.pdf(w) * (1.0 / v - 1.0 / w))

    return float(brentq(lambda x: tail(x) - alpha, mean + 0.1 * sd, mean + 100.0 * sd))


def noise_test(
    squares: Sequence[float],
    counts: Sequence[int],
    noise_samples: Sequence[int],
    nuisances: int,
    alpha: float = ALPHA,
    out_of_fold: OutOfFold = NO_FIT,
) -> NoiseTest:
    """Test per-channel sums of squared whitened residuals `squares` (with their `counts` of values); for a
    held-out residual, `out_of_fold` is what the fits on the other folds add."""
    threshold, dof = ratio_threshold(counts, noise_samples, nuisances, alpha, out_of_fold)
    return NoiseTest(float(np.sum(squares)) / dof, threshold, dof, alpha)


def out_of_fold_excess(jac: np.ndarray, folds: np.ndarray) -> OutOfFold:
    """What leave-one-fold-out linear least-squares fits add to the held-out sum of squares of white unit
    noise (see the module docstring). jac (N, k): the whitened sensitivity (rows with a non-finite entry are
    left out, as the fits leave them); folds (N,): each row's fold label.

    With U_g = S_g X M_g, M_g = (X_~g^T X_~g)^-1, and V_g = S_~g X (S selecting rows), P = U V^T and
    (I - P)^T (I - P) = I + W K W^T with W = [U V] and K = [[0, -I], [-I, U^T U]], whose non-zero
    eigenvalues are those of the small (W^T W)^(1/2) K (W^T W)^(1/2). W^T W needs only each fold's
    A_g = X_g^T X_g: U_g^T U_g = M_g A_g M_g, U_g^T V_h = M_g A_g (g != h), V_g^T V_h = sum of the A_f
    outside g and h (0 for U_g^T U_h, U_g^T V_g). X is first replaced by an orthonormal basis of its span
    (`span_basis`): the fits' predictions, so P, are the same, and the blocks are of order one (in parameter
    units, a registration offset's columns per metre, the A_g and M_g blocks differ by some 27 orders of
    magnitude and the spectrum drowns in round-off: e_j up to 4e5 where the direct trace sums them to 94)."""
    rows = np.isfinite(jac).all(axis=1)
    labels = np.asarray(folds)[rows]
    groups = np.unique(labels)
    if len(groups) < 2:
        return NO_FIT
    x = span_basis(jac[rows])
    if x.shape[1] == 0:
        return NO_FIT
    grams = [x[labels == g].T @ x[labels == g] for g in groups]
    total = np.sum(grams, axis=0)
    inverses = [np.linalg.pinv(total - a) for a in grams]
    f, k = len(groups), x.shape[1]
    gram = np.zeros((2 * f * k, 2 * f * k))
    u_block = np.zeros((f * k, f * k))

    def at(i: int, j: int) -> tuple[slice, slice]:
        return slice(i * k, (i + 1) * k), slice(j * k, (j + 1) * k)

    for g in range(f):
        u_block[at(g, g)] = gram[at(g, g)] = inverses[g] @ grams[g] @ inverses[g]
        for h in range(f):
            outside = total - grams[g] - (grams[h] if h != g else 0.0)
            gram[at(f + g, f + h)] = outside
            if h != g:
                gram[at(g, f + h)] = inverses[g] @ grams[g]
                gram[at(f + h, g)] = grams[g] @ inverses[g]
    identity = np.eye(f * k)
    kernel = np.block([[np.zeros_like(identity), -identity], [-identity, u_block]])
    values, vectors = np.linalg.eigh(gram)
    root = vectors * np.sqrt(np.clip(values, 0.0, None)) @ vectors.T
    excess = np.linalg.eigvalsh(root @ kernel @ root)
    return OutOfFold(tuple(float(e) for e in excess[np.abs(excess) > 1e-9 * np.abs(excess).max()]))


def span_basis(x: np.ndarray) -> np.ndarray:
    """(N, r) orthonormal basis of the column span of x (N, k): its left singular vectors with a singular
    value above 1e-12 of the largest (r = 0 for a zero matrix). Least-squares fits on it predict what fits
    on x predict (x = basis T, T invertible on the span)."""
    u, s, _ = np.linalg.svd(x, full_matrices=False)
    return u[:, s > 1e-12 * s.max(initial=0.0)]
