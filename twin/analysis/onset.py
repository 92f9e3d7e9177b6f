"""A registration offset from where contact begins (issue 20): no linearisation at zero, no new fe replay.

Per trajectory k, the measured loading curve (force along the press direction against commanded depth z)
is the model's curve shifted along the path: g_meas(z) = g_model(z + s_k), s_k > 0 when the skin is nearer
than the model thinks (the press reaches it earlier). The model's curve is its base replay (already
computed); s_k is the horizontal distance between the two curves over the forces both reach
(`contact_shift`: each measured increment in contact placed on the inverted model curve, weighted by the
curve's slope over the force's standard error; nothing extrapolated).

A rigid offset o (m, biotac frame) of the indenter path (the `registration_offset` effect: tips + o) moves
the tip's signed depth below the skin's tangent plane at the contact, d.(-n) z - n.o with n the outward
skin normal there and d the unit press direction, so the model reaches the same depth at z' = z -
n.o / (-n.d): to first order in the skin's curvature,

    s_k = (n_k . o) / (n_k . d_k)

(an offset into the skin, o = -e n, gives s = e / |n.d| > 0: the press is deeper). The shifts of all the
trajectories (of one arm) give o by weighted least squares (`offset_from_shifts`), weights 1 / var(s_k);
directions the presses cannot see (every n_k nearly parallel: only n.o is seen, or no press touches) are
reported in `unseen` and left at the model's value, never invented.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assets.indenters import get_indenter
from twin.analysis.data import TrajectoryRecord
from twin.analysis.predict import Predictor, TwinModel, measured_force_fullrate
from twin.analysis.residual import Base
from twin.effects import REGISTRATION, apply_skin, registration_values, registration_vector

CONTACT_SIGMAS = 5.0
"""A measured increment counts as in contact when its mean force along the press exceeds this many standard
errors."""
SHIFT_FLOOR = 0.05e-3
"""The first-order relation's own error (m) on one path's shift (skin curvature, the normal's estimate),
added in quadrature to the statistical one: without it two presses at one point, whose contact normals
differ by a few degrees, would claim to see a second direction."""
CONTACT_RADIUS = 1e-3
"""Gaussian radius (m) over which the skin's face normals are averaged about the contact point."""
UNSEEN_STD = 0.5e-3
"""A direction of the offset whose standard error exceeds this (m) is reported unseen and not estimated."""
LARGE_OFFSET = 0.5e-3
"""An estimate at least this large (m; the paper's 0.5-1.5 mm band begins here) is beyond the reach of the
linearisation at zero and is tried as a start; a smaller one is left to that linearisation. Tried at any size it
lets the offset fit a fluid-volume error in sample (more fluid lifts the skin at both points of the test campaign
alike) and outrank it: the verdict no longer names it (its held-out test fails), but with one refit the hidden
effect is then never refitted (measured, docs/analysis.md)."""


@dataclass(frozen=True)
class PathShift:
    """One trajectory's contact shift: s (m, along the path; > 0: the skin is nearer than modelled), its
    1-sigma standard error (m; inf when the path shows no usable contact), the outward skin normal n and press
    direction d (unit, biotac frame) of the relation s = n.o / n.d."""

    trajectory_id: int
    shift: float
    std: float
    normal: np.ndarray
    direction: np.ndarray

    @property
    def row(self) -> np.ndarray:
        """(3,) d s / d o = n / (n.d) (1: m of shift per m of offset)."""
        return self.normal / float(self.normal @ self.direction)


@dataclass(frozen=True)
class OnsetEstimate:
    """The registration offset the contact onsets give (m, biotac frame, on top of the model's own), its
    covariance (3, 3; m^2; zero along unseen directions), the unit directions it cannot see (rows), and the
    per-trajectory shifts it came from."""

    offset: np.ndarray
    covariance: np.ndarray
    unseen: np.ndarray
    shifts: tuple[PathShift, ...]

    def to_dict(self) -> dict:
        """JSON-ready summary: offset_m (3,), std_m (3,; 0 along unseen directions), unseen (unit rows), and
        per trajectory its shift_m and shift_std_m (null where the path shows no contact to align)."""
        return {
            "offset_m": self.offset.tolist(),
            "std_m": np.sqrt(np.clip(np.diag(self.covariance), 0.0, None)).tolist(),
            "unseen": self.unseen.tolist(),
            "shifts": [
                {"trajectory_id": s.trajectory_id, "shift_m": s.shift, "shift_std_m": s.std} for s in self.shifts
            ],
        }

    @property
    def large(self) -> bool:
        """Whether the estimate is at least `LARGE_OFFSET` (worth a start of its own)."""
        return bool(np.linalg.norm(self.offset) >= LARGE_OFFSET)

    def values(self, current: dict[str, float]) -> dict[str, float]:
        """The `registration_offset` values: `current` (the model's) moved by the estimate, within bounds."""
        return registration_values(registration_vector(current) + self.offset)

    def start(self, current: dict[str, float]) -> dict[str, float] | None:
        """`values` when the estimate is `large` (the effect's data-driven start, `sensitivity.DATA_STARTS`), else
        None."""
        return self.values(current) if self.large else None

    def estimate(self, current: dict[str, float]) -> dict[str, float]:
        """`values`, whatever the estimate's size (`sensitivity.StartEstimate.estimate`)."""
        return self.values(current)


def loading_curves(
    trajectory: TrajectoryRecord, predicted_force: np.ndarray, sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per loading increment (from the standoff to the first deepest command): commanded depth z (m), the
    measured and the predicted mean force along the press direction (N) and the measured mean's standard error
    (N) from the force noise `sigma` (3,) (N per full-rate sample, biotac frame). `predicted_force` (T, 3): the
    model's tared full-rate force on the same samples (NaN where its replay failed)."""
    raw, d = trajectory.raw, trajectory.direction
    measured = measured_force_fullrate(trajectory) @ d
    predicted = predicted_force @ d
    deepest = int(raw.increment[np.argmax(raw.depth_command)])
    increments = np.arange(-1, deepest + 1)
    z, g_meas, g_model, error = [], [], [], []
    spread = float(np.sqrt(np.sum((sigma * d) ** 2)))
    for i in increments:
        mine = raw.increment == i
        if not mine.any() or not np.isfinite(predicted[mine]).all():
            break
        z.append(float(raw.depth_command[mine][0]))
        g_meas.append(float(measured[mine].mean()))
        g_model.append(float(predicted[mine].mean()))
        error.append(spread / np.sqrt(mine.sum()))
    return np.array(z), np.array(g_meas), np.array(g_model), np.array(error)


def contact_shift(z: np.ndarray, g_meas: np.ndarray, g_model: np.ndarray, error: np.ndarray) -> tuple[float, float]:
    """(s, its 1-sigma standard error) m: the horizontal distance between the curves, g_meas(z) = g_model(z + s).

    Each measured increment whose force lies inside the model curve's loaded range (above `CONTACT_SIGMAS`
    standard errors and below the model's largest force, so nothing is extrapolated) gives s_i = z_model(g_i)
    - z_i, z_model the inverse of the model's loading curve (made non-decreasing, linear between increments),
    with variance (error_i / slope_i)^2; s is their weighted mean, its standard error the weighted mean's
    plus `SHIFT_FLOOR` (the first-order relation's own error) in quadrature; (nan, inf) without such
    increments (no contact to align)."""
    rising = np.maximum.accumulate(g_model)
    low = CONTACT_SIGMAS * float(np.max(error)) if len(error) else np.inf
    keep = np.flatnonzero(np.diff(rising) > 0)
    if len(keep) == 0:
        return float("nan"), float("inf")
    lo, hi = max(low, float(rising[keep[0]])), float(rising[-1])
    inside = (g_meas > lo) & (g_meas < hi)
    if not inside.any():
        return float("nan"), float("inf")
    # the inverse of the rising part: strictly increasing nodes only
    nodes = np.r_[keep, keep[-1] + 1]
    z_model = np.interp(g_meas[inside], rising[nodes], z[nodes])
    k = np.clip(np.searchsorted(rising[nodes], g_meas[inside]), 1, len(nodes) - 1)
    slope = (rising[nodes][k] - rising[nodes][k - 1]) / (z[nodes][k] - z[nodes][k - 1])
    weight = (slope / error[inside]) ** 2
    s = float(np.sum(weight * (z_model - z[inside])) / np.sum(weight))
    return s, float(np.sqrt(1.0 / np.sum(weight) + SHIFT_FLOOR**2))


def contact_normal(
    predictor: Predictor, model: TwinModel, trajectory: TrajectoryRecord, offset: np.ndarray
) -> np.ndarray:
    """(3,) outward unit normal of the model's outer skin (biotac frame) where the indenter first touches it
    on `trajectory`'s path moved by `offset` (m): area- and Gaussian-weighted face normals about the face
    point nearest the indenter (least signed distance) at the touch pose."""
    skin = apply_skin(model.skin, model.effects)
    surface = predictor.fe_model(skin, model.mesh_max_edge, model.inflation).outer_surface()
    centres = surface.triangles_center
    indenter = get_indenter(trajectory.indenter)
    gaps = indenter.sdf((centres - (trajectory.touch_point + offset)) @ trajectory.rotation)
    contact = centres[int(np.argmin(gaps))]
    weight = surface.area_faces * np.exp(-((np.linalg.norm(centres - contact, axis=1) / CONTACT_RADIUS) ** 2))
    normal = weight @ surface.face_normals
    return normal / np.linalg.norm(normal)


def offset_from_shifts(shifts: list[PathShift]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(offset (3,) m, covariance (3, 3) m^2, unseen directions (u, 3)) of the weighted least squares
    s_k = row_k . o over the paths with a finite shift; directions whose standard error exceeds `UNSEEN_STD`
    are unseen: the offset has no component along them and its covariance none."""
    used = [s for s in shifts if np.isfinite(s.shift) and np.isfinite(s.std)]
    if not used:
        return np.zeros(3), np.zeros((3, 3)), np.eye(3)
    a = np.array([s.row / s.std for s in used])
    b = np.array([s.shift / s.std for s in used])
    u, singular, vt = np.linalg.svd(a, full_matrices=True)
    singular = np.r_[singular, np.zeros(3)][:3]
    seen = singular > 1.0 / UNSEEN_STD
    u_b = np.r_[u.T @ b, np.zeros(3)][:3]  # the data along each right singular vector (none past the rows)
    offset, covariance = np.zeros(3), np.zeros((3, 3))
    for i in np.flatnonzero(seen):
        offset += u_b[i] / singular[i] * vt[i]
        covariance += np.outer(vt[i], vt[i]) / singular[i] ** 2
    return offset, covariance, vt[~seen]


def onset_estimate(
    predictor: Predictor, models: list[TwinModel], trajectories: list[TrajectoryRecord], sigma: np.ndarray
) -> OnsetEstimate:
    """The registration offset, on top of each trajectory's model's own (`models`, one per trajectory), that
    the contact onsets of `trajectories` give (see the module docstring); `sigma` (3+,) the force noise per
    full-rate sample (N, biotac frame; x, y, z first). Uses the cached base replays (`Predictor.predict`)."""
    shifts = []
    for model, t in zip(models, trajectories, strict=True):
        curves = loading_curves(t, predictor.predict(model, t, rows=False).force_fullrate, np.asarray(sigma)[:3])
        s, std = contact_shift(*curves)
        here = registration_vector(model.effects.get(REGISTRATION))
        shifts.append(PathShift(t.trajectory_id, s, std, contact_normal(predictor, model, t, here), t.direction))
    offset, covariance, unseen = offset_from_shifts(shifts)
    return OnsetEstimate(offset, covariance, unseen, tuple(shifts))


def onset_start(predictor: Predictor, model: TwinModel, base: Base) -> OnsetEstimate:
    """The data-driven start of `registration_offset` (`sensitivity.DATA_STARTS`): the estimate on `base`'s
    trajectories, each about its own model (`Base.model_for`: the nuisances' values where they were fitted)."""
    models = [base.model_for(model, t) for t in base.trajectories]
    return onset_estimate(predictor, models, base.trajectories, base.sigma)
