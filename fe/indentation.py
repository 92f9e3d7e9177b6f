"""Quasi-static, pose-driven indentation of a pressurised shell by a rigid indenter.

`IndentationStepper` holds the skin state between prescribed indenter poses (as a robot arm would move
the indenter): each `step` re-solves equilibrium with the fluid volume held, warm-started from the last
state, with friction lagged (normal forces and normals refreshed between Newton solves until they
settle). `indent` drives a stepper along a straight `Trajectory`. Forces are in newtons in the sensor
frame and are the force the indenter applies to the skin.
"""

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from fe.newton import NewtonResult, NewtonSettings, solve_equilibrium
from fe.shell import IndenterState, ShellSystem, lumped_areas
from fe.trapped_air import TrappedAir, TrappedAirProblem
from fe.viscoelastic import SkinRelaxation


@dataclass(frozen=True)
class IncrementResult:
    """Outputs of one increment (SI units, sensor frame)."""

    depth: float
    """Signed tip travel (m) along the indenter's local -z axis (its pressing direction) from the stepper's
    origin: the first-touch point for `indent`, else the first pose stepped after a reset."""
    force: np.ndarray
    """(3,) force of the indenter on the skin (N)."""
    pressure: float
    """Fluid pressure (Pa)."""
    volume: float
    """Enclosed volume (m^3) as the skin triangles measure it."""
    contact_area: float
    """Deformed area of skin vertices in contact with the indenter (m^2)."""
    contact_radius: float
    """Largest distance of a contact vertex from the indenter's axis (its local z through the tip) (m)."""
    displacement: np.ndarray
    """(V,3) nodal displacements from the reference (inflated) state (m)."""
    newton_iterations: int
    residual: float
    """Infinity norm of the free-DOF residual force (N)."""
    equilibrium_error: float
    """|indenter + core + anchor + pressure forces on the skin| / max(|indenter|, |pressure| force)."""
    converged: bool
    message: str
    wall_s: float


@dataclass(frozen=True)
class Trajectory:
    """A straight indentation: first-touch tip position (m), unit direction (the indenter's local -z, i.e.
    rotation[:, 2] = -direction), indenter rotation (3,3) body->sensor, depths past touch (m), and the time
    (s) of each depth (None: untimed, only for a skin without viscoelastic relaxation)."""

    touch_point: np.ndarray
    direction: np.ndarray
    rotation: np.ndarray
    depths: np.ndarray
    times: np.ndarray | None = None

    def __post_init__(self) -> None:
        if np.any(np.asarray(self.depths) < 0):
            raise ValueError("indentation depths must be non-negative")
        if self.times is not None and np.shape(self.times) != np.shape(self.depths):
            raise ValueError("a timed trajectory needs one time per depth")
        if not np.isclose(np.linalg.norm(self.direction), 1.0):
            raise ValueError("direction must be a unit vector")
        if not np.allclose(np.asarray(self.rotation)[:, 2], -np.asarray(self.direction), atol=1e-9):
            raise ValueError("the indenter presses along its local -z: rotation[:, 2] must equal -direction")


def _force_balance(system: ShellSystem, terms: dict, pressure: float) -> tuple[np.ndarray, float]:
    """Indenter force on the skin (N) and the relative error of the global force balance."""
    residual = terms["elastic_gradient"] + terms["core_gradient"] + terms["indenter_gradient"]
    residual = residual - pressure * terms["volume_gradient"]
    anchors = np.where(system.fixed_dofs, residual, 0.0).sum(axis=0)
    f_indenter = -terms["indenter_gradient"].sum(axis=0)
    f_core = -terms["core_gradient"].sum(axis=0)
    f_pressure = pressure * terms["volume_gradient"].sum(axis=0)
    imbalance = np.linalg.norm(f_indenter + f_core + f_pressure + anchors)
    scale = max(np.linalg.norm(f_indenter), np.linalg.norm(f_pressure), 1e-300)
    return f_indenter, float(imbalance / scale)


def _check_pose(rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validated copies of an indenter pose: a proper rotation (3,3) and a finite tip position (3,) (m)."""
    rotation = np.array(rotation, dtype=np.float64)
    translation = np.array(translation, dtype=np.float64)
    if rotation.shape != (3, 3) or translation.shape != (3,):
        raise ValueError("an indenter pose is a rotation (3,3) and a translation (3,)")
    if not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(translation))):
        raise ValueError("indenter pose has non-finite entries")
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-8) or np.linalg.det(rotation) < 0:
        raise ValueError("indenter rotation must be orthonormal with determinant +1")
    return rotation, translation


class IndentationStepper:
    """Skin equilibrium under a sequence of prescribed rigid indenter poses, starting from the inflated state.

    Poses are in the sensor frame: `rotation` (3,3) maps the indenter body frame (tip at the origin, body
    along +z, pressing along -z) to the sensor frame and `translation` (3,) is the tip position (m). Each
    `step` solves quasi-static equilibrium with the fluid volume held at `target_volume` (m^3), warm-started
    from the previous state, friction lagged; the friction slip is measured relative to the indenter's
    motion since the previous pose. A pose with no skin vertex inside the contact band (gap < 0) while the
    skin is free and relaxed costs no Newton work. After a step that does not converge the stepper refuses
    further steps until `reset()`.

    Effects of the system's `SkinParameters`: viscoelastic relaxation (relaxation_fraction > 0) makes the
    response depend on the time of each step (`time_s`), and `air` (a bubble in the fluid, see
    `fe.trapped_air`) makes the held volume the liquid's, target_volume - air.volume(pressure_reference).
    """

    def __init__(
        self,
        system: ShellSystem,
        x_reference: np.ndarray,
        pressure_reference: float,
        target_volume: float,
        kind: int,
        dims: tuple[float, float, float, float],
        offset: float,
        newton: NewtonSettings = NewtonSettings(),
        origin: np.ndarray | None = None,
        air: TrappedAir | None = None,
    ) -> None:
        """`x_reference` (V,3) m and `pressure_reference` (Pa): the inflated state; `offset` (m): skin
        half-thickness outside the mid-surface; `origin` (3,) m: tip position of zero depth (None: the first
        pose stepped after each reset); `air`: trapped air in the cavity (None: none)."""
        self.system = system
        self.x_reference = np.array(x_reference, dtype=np.float64)
        self.pressure_reference = float(pressure_reference)
        self.target_volume = float(target_volume)
        self.kind, self.dims, self.offset, self.newton = kind, tuple(dims), float(offset), newton
        self._fixed_origin = None if origin is None else np.array(origin, dtype=np.float64)
        self._problem = system if air is None else TrappedAirProblem(system, air)
        if air is not None:
            self.target_volume -= air.volume(self.pressure_reference)
        p = system.params
        self.relaxation = None
        if p.relaxation_fraction > 0.0:
            self.relaxation = SkinRelaxation(system, np.array([p.relaxation_fraction]), np.array([p.relaxation_time_s]))
            self.relaxation.reset(self.x_reference)
        system.indenter = None
        terms = system.evaluate(self.x_reference, want_hessian=False)
        self._rest_volume = float(terms["volume"])
        self._rest_balance = _force_balance(system, terms, self.pressure_reference)[1]
        lin = system.linearize(system.free_coordinates(self.x_reference), self.pressure_reference, want_matrix=False)
        self._rest_residual = float(np.max(np.abs(lin.gradient - self.pressure_reference * lin.volume_gradient)))
        self.reset()

    def reset(self) -> None:
        """Back to the inflated reference state, indenter released, ready to step again.

        State kept between steps: `x` (V,3) skin mid-surface positions (m), `pressure` (Pa), `pose` (the
        last (rotation, translation) or None), `in_contact`, `time_s` (of the last step, None when untimed),
        `failure` (message of a non-converged step), and the viscoelastic branches (relaxed again here).
        """
        self.pose: tuple[np.ndarray, np.ndarray] | None = None
        self.failure: str | None = None
        self.time_s: float | None = None
        self._release()
        if self.relaxation is not None:
            self.relaxation.reset(self.x_reference)
        self._origin = None if self._fixed_origin is None else self._fixed_origin.copy()

    def step(self, rotation: np.ndarray, translation: np.ndarray, time_s: float | None = None) -> IncrementResult:
        """Move the indenter to the pose (rotation (3,3) body->sensor, tip position (3,) m) at time `time_s`
        (s, any clock, non-decreasing between steps; None: no time passes) and re-solve.

        With viscoelastic relaxation `time_s` is required; the first step after a reset starts the clock
        (the inflated state is fully relaxed). Stepping the same pose at a later time lets the skin relax.
        """
        if self.failure is not None:
            raise RuntimeError(f"the last step did not converge ({self.failure}); call reset() before stepping again")
        rotation, translation = _check_pose(rotation, translation)
        dt = self._clock(time_s)
        start = time.perf_counter()
        if self._origin is None:
            self._origin = translation.copy()
        rotation_start, translation_start = self.pose if self.pose is not None else (rotation, translation)
        indenter = IndenterState(
            self.kind, self.dims, rotation, translation, translation_start, self.offset, rotation_start
        )
        self.pose = (rotation, translation)
        depth = float((self._origin - translation) @ rotation[:, 2])
        free_now = self.system.indenter_proximity(self.x, indenter)[0].min(initial=np.inf) >= 0.0
        relaxed = self.relaxation is None or self.relaxation.at_rest
        if free_now and not self.in_contact and relaxed:
            return self._free_result(depth, start)
        if (
            free_now
            and self.relaxation is None
            and self.system.indenter_proximity(self.x_reference, indenter)[0].min(initial=np.inf) >= 0.0
        ):
            # The inflated state is an equilibrium that the indenter does not touch: release to it. (A skin
            # with viscoelastic memory creeps back instead, which the solve follows.)
            self._release()
            return self._free_result(depth, start)
        if self.relaxation is not None:
            self.relaxation.prepare(dt)
        return self._finish(indenter, self._solve(indenter), depth, dt, start)

    def _clock(self, time_s: float | None) -> float:
        """Time (s) since the last step, validating and recording `time_s`."""
        if time_s is None:
            if self.relaxation is not None:
                raise ValueError("a viscoelastic skin (relaxation_fraction > 0) needs the time_s of every step")
            return 0.0
        time_s = float(time_s)
        if not np.isfinite(time_s):
            raise ValueError(f"time_s={time_s} must be finite")
        if self.time_s is not None and time_s < self.time_s:
            raise ValueError(f"time_s={time_s} s goes back from the last step's {self.time_s} s")
        dt = 0.0 if self.time_s is None else time_s - self.time_s
        self.time_s = time_s
        return dt

    def _release(self) -> None:
        """Put the skin back to the inflated reference state, keeping the indenter pose and depth origin."""
        self.x = self.x_reference.copy()
        self.pressure = self.pressure_reference
        self.in_contact = False
        self._motion: np.ndarray | None = None
        self._travel = np.zeros(3)
        self._gap = np.zeros(len(self.x))
        self._gap_change = np.zeros(len(self.x))

    def _predict(self, indenter: IndenterState) -> np.ndarray:
        """Warm start (V,3) m for the new pose: the last solved increment's displacement extrapolated by the
        share of its tip travel that the new move repeats, then every vertex that would sit deeper in the
        indenter than it did at the last equilibrium pushed out along the SDF normal to that depth; fixed DOFs
        stay where they are."""
        x = self.x.copy()
        travel = indenter.translation - indenter.translation_start
        share = 0.0
        if self._motion is not None and self._travel @ self._travel > 0.0:
            share = float(np.clip((travel @ self._travel) / (self._travel @ self._travel), 0.0, 1.0))
            x += share * self._motion
        gap, normal = self.system.indenter_proximity(x, indenter)
        depth = np.minimum(self._gap + share * self._gap_change, 0.0)
        x += np.maximum(depth - gap, 0.0)[:, None] * normal
        return np.where(self.system.fixed_dofs, self.x, x)

    def _solve(self, indenter: IndenterState) -> NewtonResult:
        """One Newton solve at the new pose from the predicted state, the friction normal forces and
        normals refreshed inside it (at most `friction_passes` times) until they settle."""
        system, cs = self.system, self.system.contact_settings
        system.x_start = self.x.copy()
        system.indenter = indenter
        x0 = self._predict(indenter)
        self._lag_contact(x0)
        passes = 0

        def refresh(q: np.ndarray) -> bool:
            nonlocal passes
            if passes >= cs.friction_passes:
                return False
            passes += 1
            return self._lag_contact(system.positions(q))

        return solve_equilibrium(
            self._problem,
            system.free_coordinates(x0),
            self.pressure,
            self.target_volume,
            self.newton,
            refresh=refresh if system.params.friction > 0.0 else None,
        )

    def _lag_contact(self, x: np.ndarray) -> bool:
        """Set the lagged friction normal forces (N) and normals from positions x (V,3) m; returns whether
        the forces changed by more than the friction tolerance (relative to the largest one)."""
        system, cs = self.system, self.system.contact_settings
        gap, normal = system.indenter_proximity(x, system.indenter)
        force = cs.penalty_stiffness * system.vertex_area * np.maximum(-gap, 0.0)
        change = np.max(np.abs(force - system.lagged_force), initial=0.0)
        if change <= cs.friction_tolerance * max(force.max(initial=0.0), 1e-12):
            return False
        system.lagged_force, system.lagged_normal = force, normal
        return True

    def _finish(
        self, indenter: IndenterState, result: NewtonResult, depth: float, dt: float, start: float
    ) -> IncrementResult:
        """Accept a converged solve dt (s) after the last state as the new state (or record the failure) and
        report it."""
        system = self.system
        x = system.positions(result.q)
        terms = system.evaluate(x, want_hessian=False)
        f_indenter, balance = _force_balance(system, terms, result.pressure)
        in_contact = terms["indenter_gap"] < 0.0
        if result.converged:
            self._motion, self._travel = x - self.x, indenter.translation - indenter.translation_start
            self._gap_change = np.minimum(terms["indenter_gap"], 0.0) - np.minimum(self._gap, 0.0)
            self._gap = terms["indenter_gap"]
            self.x, self.pressure, self.in_contact = x, result.pressure, bool(in_contact.any())
            if self.relaxation is not None:
                self.relaxation.advance(dt, x)
        else:
            self.failure = result.message
        axis = indenter.rotation[:, 2]
        rel = x - indenter.translation
        radial = rel - np.outer(np.einsum("ij,j->i", rel, axis), axis)  # einsum: no BLAS thread wake-ups
        return IncrementResult(
            depth=depth,
            force=f_indenter,
            pressure=float(result.pressure),
            volume=float(terms["volume"]),
            contact_area=float(lumped_areas(x, system.mesh.triangles)[in_contact].sum()),
            contact_radius=float(np.linalg.norm(radial[in_contact], axis=1).max(initial=0.0)),
            displacement=x - self.x_reference,
            newton_iterations=result.iterations,
            residual=result.residual_norm,
            equilibrium_error=balance,
            converged=result.converged,
            message=result.message,
            wall_s=time.perf_counter() - start,
        )

    def _free_result(self, depth: float, start: float) -> IncrementResult:
        """The report of a pose that leaves the (free, inflated) skin untouched: no Newton work."""
        return IncrementResult(
            depth=depth,
            force=np.zeros(3),
            pressure=self.pressure,
            volume=self._rest_volume,
            contact_area=0.0,
            contact_radius=0.0,
            displacement=self.x - self.x_reference,
            newton_iterations=0,
            residual=self._rest_residual,
            equilibrium_error=self._rest_balance,
            converged=True,
            message="no contact",
            wall_s=time.perf_counter() - start,
        )


def indent(
    system: ShellSystem,
    x_reference: np.ndarray,
    pressure_reference: float,
    target_volume: float,
    kind: int,
    dims: tuple[float, float, float, float],
    trajectory: Trajectory,
    offset: float,
    newton: NewtonSettings = NewtonSettings(),
) -> Iterator[IncrementResult]:
    """Yield one result per depth of a straight trajectory; stop after the first increment that does not
    converge. A thin loop over an `IndentationStepper` whose depth origin is the first-touch point."""
    stepper = IndentationStepper(
        system, x_reference, pressure_reference, target_volume, kind, dims, offset, newton, trajectory.touch_point
    )
    yield from drive(stepper, trajectory)


def drive(stepper: IndentationStepper, trajectory: Trajectory) -> Iterator[IncrementResult]:
    """Step `stepper` through the poses (and times) of a straight trajectory, yielding each increment;
    stop after the first one that does not converge."""
    for k, depth in enumerate(trajectory.depths):
        time_s = None if trajectory.times is None else trajectory.times[k]
        result = stepper.step(trajectory.rotation, trajectory.touch_point + depth * trajectory.direction, time_s)
        yield result
        if not result.converged:
            return
