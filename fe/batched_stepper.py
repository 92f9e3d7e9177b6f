"""Pose-driven indentation of B trajectories at once: the batched counterpart of `fe.indentation.IndentationStepper`.

`BatchedStepper.step(rotations, translations, active)` moves each active system's indenter to its pose and
re-solves all of them together on the warp device, with the per-system logic of the single stepper: a
pose that does not touch the free skin costs no Newton work, leaving contact releases to the inflated
state, the warm start extrapolates the last increment and pushes vertices out of the indenter, the
friction slip is measured from the previous pose, and a system whose step fails refuses further steps
until `reset`. Poses: rotation (3,3) indenter body -> sensor frame, tip position (3,) m; results are
`fe.indentation.IncrementResult`s (forces in N, sensor frame), `wall_s` being the whole batch step's time.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
import warp as wp

from assets.indenters import get_indenter
from fe.batched import BatchedShell, InflatedSkin
from fe.indentation import IncrementResult


def _check_poses(
    rotation: np.ndarray, translation: np.ndarray, batch: int, active: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Copies of B poses, rotations (B,3,3) and tip positions (B,3) m; the active ones must be proper
    rotations and finite (inactive rows are ignored)."""
    rotation = np.array(rotation, dtype=np.float64)
    translation = np.array(translation, dtype=np.float64)
    if rotation.shape != (batch, 3, 3) or translation.shape != (batch, 3):
        raise ValueError(f"poses are rotations ({batch},3,3) and translations ({batch},3)")
    rot, trans = rotation[active], translation[active]
    if not (np.all(np.isfinite(rot)) and np.all(np.isfinite(trans))):
        raise ValueError("indenter poses have non-finite entries")
    gram = np.einsum("bji,bjk->bik", rot, rot)
    if not np.allclose(gram, np.eye(3), atol=1e-8) or np.any(np.linalg.det(rot) < 0):
        raise ValueError("indenter rotations must be orthonormal with determinant +1")
    return rotation, translation


class BatchedStepper:
    """B independent indentation trajectories of one inflated skin, stepped together on `device`.

    `indenters`: one indenter name per system (keep equal names contiguous: one contact launch per run).
    """

    def __init__(self, skin: InflatedSkin, indenters: Sequence[str], device: str = "cpu") -> None:
        shapes = [get_indenter(name) for name in indenters]
        self.skin, self.batch = skin, len(shapes)
        if self.batch == 0:
            raise ValueError("a batch needs at least one trajectory")
        self.shell = BatchedShell(skin, [(s.kind, s.dims) for s in shapes], device)
        V, T = len(skin.vertices), len(skin.triangles)
        rows = skin.triangles.ravel()
        # (V, T) incidence / 3: lumped vertex areas of B deformed meshes in one product.
        self._lump = sp.csr_matrix((np.full(3 * T, 1.0 / 3.0), (rows, np.repeat(np.arange(T), 3))), shape=(V, T))
        self._reference = np.broadcast_to(skin.reference, (self.batch, V, 3))
        self._reference_w = wp.array(self._reference, dtype=wp.vec3d, device=device)
        self.shell.x.assign(self._reference)
        rest = self.shell.evaluate(self._reference_w, False, np.full(self.batch, skin.pressure))
        self._rest_volume, self._rest_residual = float(rest.volume[0]), float(rest.residual_inf[0])
        self._rest_balance = float(self._force_balance(np.full(self.batch, skin.pressure))[1][0])
        B, V = self.batch, len(skin.vertices)
        self.x = self._reference.copy()
        """(B,V,3) skin mid-surface positions (m) of the last accepted state."""
        self.pressure = np.full(B, skin.pressure)
        self.pose_rotation, self.pose_translation = np.tile(np.eye(3), (B, 1, 1)), np.zeros((B, 3))
        self.posed = np.zeros(B, dtype=bool)
        """Whether a system has been stepped since its reset (its pose is the start of the next increment)."""
        self.origin, self.has_origin = np.zeros((B, 3)), np.zeros(B, dtype=bool)
        self.failure: list[str | None] = [None] * B
        self.in_contact = np.zeros(B, dtype=bool)
        self._motion, self._has_motion, self._travel = np.zeros((B, V, 3)), np.zeros(B, dtype=bool), np.zeros((B, 3))
        self._gap, self._gap_change = np.zeros((B, V)), np.zeros((B, V))

    # -- state -------------------------------------------------------------------------------------
    def reset(self, which: np.ndarray | None = None) -> None:
        """Back to the inflated state, indenter released and depth origin cleared, for `which` systems (all)."""
        which = np.ones(self.batch, dtype=bool) if which is None else np.asarray(which, dtype=bool)
        self.posed[which] = False
        self.has_origin[which] = False
        for i in np.flatnonzero(which):
            self.failure[i] = None
        self._release(which)

    def _release(self, which: np.ndarray) -> None:
        """Put the systems in `which` back to the inflated state, keeping their poses and depth origins."""
        self.x[which] = self.skin.reference
        self.pressure[which] = self.skin.pressure
        self.in_contact[which] = False
        self._has_motion[which] = False
        self._travel[which] = 0.0
        self._gap[which] = 0.0
        self._gap_change[which] = 0.0

    # -- stepping ----------------------------------------------------------------------------------
    def step(
        self, rotation: np.ndarray, translation: np.ndarray, active: np.ndarray | None = None
    ) -> list[IncrementResult | None]:
        """Move each active system's indenter to its pose (B,3,3), (B,3) m and re-solve; None for inactive ones."""
        start = time.perf_counter()
        active = np.ones(self.batch, dtype=bool) if active is None else np.asarray(active, dtype=bool).copy()
        failed = [i for i in np.flatnonzero(active) if self.failure[i] is not None]
        if failed:
            raise RuntimeError(f"systems {failed} did not converge last step; reset() them before stepping again")
        rotation, translation = _check_poses(rotation, translation, self.batch, active)
        new_origin = active & ~self.has_origin
        self.origin[new_origin] = translation[new_origin]
        self.has_origin |= new_origin
        moved = active & self.posed
        rotation_start = np.where(moved[:, None, None], self.pose_rotation, rotation)
        translation_start = np.where(moved[:, None], self.pose_translation, translation)
        self.pose_rotation[active], self.pose_translation[active] = rotation[active], translation[active]
        self.posed |= active
        depth = np.einsum("bi,bi->b", self.origin - translation, rotation[:, :, 2])
        shell = self.shell
        shell.set_poses(self.pose_rotation, self.pose_translation, rotation_start, translation_start)
        free_now = shell.proximity(self._upload(self.x))[0].min(axis=1) >= 0.0
        free_ref = shell.proximity(self._reference_w)[0].min(axis=1) >= 0.0
        untouched = active & free_now & ~self.in_contact
        released = active & free_now & self.in_contact & free_ref
        self._release(released)
        solving = active & ~untouched & ~released
        results: list[IncrementResult | None] = [None] * self.batch
        if solving.any():
            self._solve(solving, translation - translation_start)
            solved = self._finish(solving, depth, rotation, translation, translation_start, start)
            for i in np.flatnonzero(solving):
                results[i] = solved[i]
        wall = time.perf_counter() - start
        for i in np.flatnonzero(untouched | released):
            results[i] = self._free_result(i, depth[i], wall)
        return results

    def _upload(self, x: np.ndarray) -> wp.array:
        self.shell.x_trial.assign(x)
        return self.shell.x_trial

    def _predict(self, solving: np.ndarray, travel: np.ndarray) -> np.ndarray:
        """Warm starts (B,V,3) m: the last increment's displacement extrapolated by the share of its tip travel
        that the new move repeats, then vertices deeper in the indenter than at the last equilibrium pushed out."""
        moved = np.einsum("bi,bi->b", self._travel, self._travel)
        share = np.where(
            self._has_motion & (moved > 0.0),
            np.clip(np.einsum("bi,bi->b", travel, self._travel) / np.where(moved > 0.0, moved, 1.0), 0.0, 1.0),
            0.0,
        )
        x = self.x + share[:, None, None] * np.where(self._has_motion[:, None, None], self._motion, 0.0)
        gap, normal = self.shell.proximity(self._upload(x))
        depth = np.minimum(self._gap + share[:, None] * self._gap_change, 0.0)
        x = x + np.maximum(depth - gap, 0.0)[:, :, None] * normal
        return np.where(solving[:, None, None], x, self.x)

    def _solve(self, solving: np.ndarray, travel: np.ndarray) -> None:
        shell = self.shell
        shell.x_start.assign(self.x)
        x0 = self._predict(solving, travel)
        shell.x.assign(x0)
        friction = self.skin.params.friction > 0.0
        shell.lag_contact(shell.x, solving)
        self._newton = shell.solve(self.pressure, np.full(self.batch, self.skin.target_volume), solving, friction)

    def _force_balance(self, pressure: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indenter forces (B,3) N and relative force-balance errors (B,) of the last evaluation."""
        g = self.shell.gradients.numpy()
        gv = self.shell.buf["volume_gradient"].numpy()
        residual = g.sum(axis=0) - pressure[:, None, None] * gv
        anchors = np.where(self.shell.fixed[None], residual, 0.0).sum(axis=1)
        f_indenter, f_core = -g[2].sum(axis=1), -g[1].sum(axis=1)
        f_pressure = pressure[:, None] * gv.sum(axis=1)
        imbalance = np.linalg.norm(f_indenter + f_core + f_pressure + anchors, axis=1)
        scale = np.maximum(np.maximum(np.linalg.norm(f_indenter, axis=1), np.linalg.norm(f_pressure, axis=1)), 1e-300)
        return f_indenter, imbalance / scale

    def _finish(
        self,
        solving: np.ndarray,
        depth: np.ndarray,
        rotation: np.ndarray,
        translation: np.ndarray,
        translation_start: np.ndarray,
        start: float,
    ) -> list[IncrementResult | None]:
        """Accept converged systems as their new state (or record failures) and report them."""
        shell, newton = self.shell, self._newton
        x = shell.x.numpy().copy()
        terms = shell.evaluate(shell.x, False, newton.pressure)
        force, balance = self._force_balance(newton.pressure)
        gap = shell.buf["indenter_gap"].numpy().copy()
        in_contact = gap < 0.0
        ok = solving & newton.converged
        self._motion[ok] = x[ok] - self.x[ok]
        self._has_motion |= ok
        self._travel[ok] = (translation - translation_start)[ok]
        self._gap_change[ok] = np.minimum(gap[ok], 0.0) - np.minimum(self._gap[ok], 0.0)
        self._gap[ok] = gap[ok]
        self.x[ok], self.pressure[ok] = x[ok], newton.pressure[ok]
        self.in_contact[ok] = in_contact[ok].any(axis=1)
        for i in np.flatnonzero(solving & ~newton.converged):
            self.failure[i] = newton.message[i]
        p0, p1, p2 = (x[:, self.skin.triangles[:, k]] for k in range(3))
        areas = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=2)  # (B, T)
        vertex_area = (self._lump @ areas.T).T
        axis = rotation[:, :, 2]
        rel = x - translation[:, None, :]
        radial = rel - np.einsum("bv,bi->bvi", np.einsum("bvi,bi->bv", rel, axis), axis)
        radius = np.where(in_contact, np.linalg.norm(radial, axis=2), 0.0).max(axis=1)
        wall = time.perf_counter() - start
        results: list[IncrementResult | None] = [None] * self.batch
        for i in np.flatnonzero(solving):
            results[i] = IncrementResult(
                depth=float(depth[i]),
                force=force[i],
                pressure=float(newton.pressure[i]),
                volume=float(terms.volume[i]),
                contact_area=float(vertex_area[i][in_contact[i]].sum()),
                contact_radius=float(radius[i]),
                displacement=x[i] - self.skin.reference,
                newton_iterations=int(newton.iterations[i]),
                residual=float(newton.residual[i]),
                equilibrium_error=float(balance[i]),
                converged=bool(newton.converged[i]),
                message=newton.message[i],
                wall_s=wall,
            )
        return results

    def _free_result(self, i: int, depth: float, wall: float) -> IncrementResult:
        return IncrementResult(
            depth=float(depth),
            force=np.zeros(3),
            pressure=float(self.pressure[i]),
            volume=self._rest_volume,
            contact_area=0.0,
            contact_radius=0.0,
            displacement=self.x[i] - self.skin.reference,
            newton_iterations=0,
            residual=self._rest_residual,
            equilibrium_error=self._rest_balance,
            converged=True,
            message="no contact",
            wall_s=wall,
        )
