"""The BioTac finite-element model: inflate the skin to the sensor's thickness, then indent it.

Frames: everything in the `biotac` frame of the product manual (x distal, -z ventral), metres.
Inflation raises the fluid volume (volume control) until the sensor is 15.1 mm thick, or, in the
paper's thermal parametrisation, by dV = beta_T (T_fl - T_ref) V_cavity.
"""

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np
import trimesh

from assets.biotac import BioTacGeometry, vertex_normals
from assets.indenters import Indenter, get_indenter
from fe.batched import InflatedSkin
from fe.batched_stepper import BatchedStepper
from fe.indentation import IncrementResult, IndentationStepper, Trajectory, drive
from fe.params import ContactSettings, NewtonSettings, SkinParameters
from fe.surface_quadrature import rule
from fe.trapped_air import TrappedAir
from fe.wptypes import host_device

SENSOR_THICKNESS = 15.1e-3
"""Manufacturer's total sensor thickness after pressurisation (m)."""
MAX_PROJECTION_DISTANCE = 3e-3
"""A requested indentation point may lie at most this far (m) from the inflated skin."""


@dataclass(frozen=True)
class InflationResult:
    """Inflated state: added fluid volume (m^3), pressure (Pa), thickness (m), equivalent T_fl (C)."""

    volume_change: float
    pressure: float
    thickness: float
    equivalent_temperature: float
    converged: bool
    message: str


class BioTacModel:
    """Skin shell + fluid + rigid core of one BioTac, solved by the FE engine (`fe.batched_stepper`).

    Use `inflate()` once (on warp's CPU device), then `stepper(...)` or `indent(...)` as often as needed on
    any device; each trajectory starts from the inflated reference state.
    """

    def __init__(
        self,
        geometry: BioTacGeometry,
        params: SkinParameters = SkinParameters(),
        contact: ContactSettings = ContactSettings(),
        newton: NewtonSettings = NewtonSettings(),
    ) -> None:
        self.geometry = geometry
        self.params = params
        self.newton = newton
        self._thermal_volume = params.thermal_expansion * geometry.cavity_volume_reference
        """beta_T V_cavity (m^3/C): the fluid volume the thermal parametrisation adds per degree."""
        skin, core = geometry.skin, geometry.core
        self.rest_skin = InflatedSkin.at_rest(
            skin.vertices,
            skin.triangles,
            skin.anchored,
            params,
            contact,
            newton,
            core=(core.vertices, core.triangles, geometry.core_gap),
            volume_origin=core.vertices.mean(axis=0),
        )
        """The unpressurised skin (its rest mesh as the starting state)."""
        # the indenter stays away; on warp's CPU device unless this machine's warp cannot compile for it
        self._inflation = BatchedStepper(self.rest_skin, ["sphere_medium"], host_device())
        self._volume0 = float(self._inflation.rest_volumes[0])
        self.reference: np.ndarray | None = None
        self.pressure = 0.0
        self.target_volume = self._volume0
        self._inflated: InflatedSkin | None = None
        self._outer: tuple[np.ndarray, trimesh.Trimesh] | None = None

    # -- inflation ---------------------------------------------------------------------------
    def _outer_vertices(self, x: np.ndarray) -> np.ndarray:
        """The outer skin surface's vertices (V,3) m: mid-surface x offset by t/2 along the vertex normals."""
        return x + 0.5 * self.params.thickness * vertex_normals(x, self.geometry.skin.triangles)

    def thickness(self, x: np.ndarray) -> float:
        """Sensor thickness (m): fixed dorsal top minus the lowest point of the outer skin surface."""
        return float(self.geometry.dorsal_top_z - self._outer_vertices(x)[:, 2].min())

    def _solve_volume(self, volume: float, start_volume: float, splits: int = 4) -> tuple[bool, str]:
        """Equilibrium at `volume` (m^3) from the state held at `start_volume`; a jump that does not converge
        is split in two, at most `splits` times deep. Returns (converged, Newton's message)."""
        converged, message = self._inflation.hold_volume(np.array([volume]))
        if converged[0] or splits == 0:
            return bool(converged[0]), message[0]
        middle = 0.5 * (start_volume + volume)
        half = self._solve_volume(middle, start_volume, splits - 1)
        if not half[0]:
            return half
        return self._solve_volume(volume, middle, splits - 1)

    def inflate(self, target_thickness: float | None = SENSOR_THICKNESS, volume_step: float = 0.02) -> InflationResult:
        """Inflate to `target_thickness` (m), or by the thermal rule when it is None; the added fluid volume is
        then scaled by `SkinParameters.inflation_volume_scale` (the fill / pretension knob).

        Volume steps are `volume_step` of the initial enclosed volume until the thickness is bracketed,
        then secant refinement to 1 um. The skin has its long-term (fully relaxed) moduli.
        """
        self._inflation.reset()
        v = self._volume0
        if target_thickness is None:
            if self._thermal_volume <= 0:
                raise ValueError("thermal inflation needs a geometry with a positive cavity_volume_reference")
            dv_total = self._thermal_volume * (self.params.fluid_temperature - self.params.reference_temperature)
            return self._fill(v, v + self.params.inflation_volume_scale * dv_total, volume_step)
        lo_v, lo_t = v, self.thickness(self._inflation.x[0])
        if target_thickness <= lo_t:
            raise ValueError(f"target thickness {target_thickness * 1e3:.2f} mm is below the unpressurised one")
        for _ in range(200):
            hi_v = lo_v + volume_step * abs(self._volume0)
            converged, message = self._solve_volume(hi_v, lo_v)
            if not converged:
                return self._finish(lo_v, False, f"inflation stalled: {message}")
            hi_t = self.thickness(self._inflation.x[0])
            if hi_t >= target_thickness:
                break
            lo_v, lo_t = hi_v, hi_t
        else:
            return self._finish(lo_v, False, "target thickness not reached")
        state_v = hi_v
        for _ in range(30):
            v = lo_v + (target_thickness - lo_t) * (hi_v - lo_v) / (hi_t - lo_t)
            converged, message = self._solve_volume(v, state_v)
            if not converged:
                return self._finish(state_v, False, f"inflation refinement failed: {message}")
            state_v = v
            t_now = self.thickness(self._inflation.x[0])
            if abs(t_now - target_thickness) < 1e-6:
                break
            if t_now < target_thickness:
                lo_v, lo_t = v, t_now
            else:
                hi_v, hi_t = v, t_now
        if self.params.inflation_volume_scale == 1.0:
            return self._finish(v, True, "converged")
        filled = self._volume0 + self.params.inflation_volume_scale * (v - self._volume0)
        return self._fill(v, filled, volume_step)

    def _fill(self, v: float, volume: float, volume_step: float) -> InflationResult:
        """Walk from the state at volume v to `volume` (m^3) in steps of at most `volume_step` of the initial
        enclosed volume, and take the end as the inflated state."""
        n_steps = max(1, int(np.ceil(abs(volume - v) / (volume_step * abs(self._volume0)))))
        converged, message = True, "converged"
        for target in np.linspace(v, volume, n_steps + 1)[1:]:
            converged, message = self._solve_volume(target, v)
            if not converged:
                break
            v = target
        return self._finish(v, converged, message)

    def _finish(self, volume: float, converged: bool, message: str) -> InflationResult:
        self.reference = self._inflation.x[0].copy()
        self.pressure = float(self._inflation.pressure[0])
        self.target_volume = volume
        self._inflated = None
        dv = volume - self._volume0
        rise = dv / self._thermal_volume if self._thermal_volume > 0 else float("nan")
        t_eq = self.params.reference_temperature + rise  # C
        return InflationResult(dv, self.pressure, self.thickness(self.reference), t_eq, converged, message)

    def inflated_skin(self) -> InflatedSkin:
        """The inflated state as the engine's starting state (inflate() first)."""
        reference = self._require_reference()
        if self._inflated is None or self._inflated.reference is not reference:
            self._inflated = replace(
                self.rest_skin,
                reference=reference,
                pressure=self.pressure,
                target_volume=self.target_volume,
                air_boyle=self.air_boyle(),
            )
        return self._inflated

    # -- indentation -------------------------------------------------------------------------
    def outer_surface(self) -> trimesh.Trimesh:
        """Inflated outer skin surface (m): mid-surface offset by t/2 along the vertex normals (one mesh per
        inflated state, so its spatial index is built once)."""
        x = self._require_reference()
        if self._outer is None or self._outer[0] is not x:
            self._outer = (x, trimesh.Trimesh(self._outer_vertices(x), self.geometry.skin.triangles, process=False))
        return self._outer[1]

    def _require_reference(self) -> np.ndarray:
        if self.reference is None:
            raise RuntimeError("inflate() the model before indenting it")
        return self.reference

    def plan_trajectory(
        self, indenter: Indenter, point: np.ndarray, angle_deg: float, azimuth_deg: float, depth: float, step: float
    ) -> Trajectory:
        """Straight trajectory to `point` (m, biotac frame), tilted `angle_deg` from the inward normal."""
        if depth < 0 or step <= 0:
            raise ValueError("depth must be >= 0 and step > 0")
        if not 0.0 <= angle_deg < 90.0:
            raise ValueError("angle must be in [0, 90) degrees")
        surface = self.outer_surface()
        closest, distance, face = trimesh.proximity.closest_point(surface, np.asarray(point, dtype=float)[None])
        if distance[0] > MAX_PROJECTION_DISTANCE:
            raise ValueError(
                f"point {np.round(np.asarray(point) * 1e3, 2)} mm is {distance[0] * 1e3:.2f} mm from the skin "
                f"(at most {MAX_PROJECTION_DISTANCE * 1e3:.0f} mm allowed)"
            )
        if self.geometry.skin.anchored[surface.faces[face[0]]].all():
            raise ValueError("point lies on the anchored (dorsal/proximal) skin, which cannot be indented")
        normal = surface.face_normals[face[0]]
        distal = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
        t1 = distal / np.linalg.norm(distal) if np.linalg.norm(distal) > 1e-6 else np.cross(normal, [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(normal, t1)
        a, az = np.radians(angle_deg), np.radians(azimuth_deg)
        direction = -np.cos(a) * normal + np.sin(a) * (np.cos(az) * t1 + np.sin(az) * t2)
        ez = -direction
        ex = t1 - (t1 @ ez) * ez
        ex /= np.linalg.norm(ex)
        rotation = np.column_stack([ex, np.cross(ez, ex), ez])
        touch = self._first_touch(indenter, rotation, closest[0], direction)
        depths = np.arange(0, int(round(depth / step)) + 1) * step
        return Trajectory(touch, direction, rotation, depths)

    def _first_touch(
        self, indenter: Indenter, rotation: np.ndarray, point: np.ndarray, direction: np.ndarray
    ) -> np.ndarray:
        """Tip position (m) where the rigid indenter first touches the undeformed outer skin: where its contact
        law first acts, at a skin vertex or a quadrature point of a skin triangle (`fe.surface_quadrature`).

        Bisection on the offset s (m) along `direction`, in the last 1 mm step back (at most 30 mm) from the first
        offset at which the contact acts to an offset at which it does not. The points that cannot hold the
        smallest gap anywhere in the remaining bracket are dropped as it narrows (the SDF changes by at most
        |ds| per ds of offset, taken with a factor of 2 of safety), so the bracket's decisions, and the
        touch point, are those of the search over every point at a fraction of its cost."""
        vertices = self._require_reference()
        weights = rule(self.rest_skin.contact.surface_rule)[:, :3]
        points = np.einsum("qk,tkd->tqd", weights, vertices[self.geometry.skin.triangles]).reshape(-1, 3)
        x = np.concatenate([vertices, points])
        half_t = self.rest_skin.indenter_half_layer

        def gaps(s: float, at: np.ndarray) -> np.ndarray:
            return indenter.sdf((at - (point + s * direction)) @ rotation) - half_t

        step, lo, hi = 1e-3, None, 0.0
        while gaps(hi, x).min() > 0:  # forward to the first offset at which the contact acts
            lo, hi = hi, hi + step
        while lo is None:  # it acts at 0: back to the last offset at which it does not
            if hi <= -30e-3:
                raise ValueError("indenter overlaps the skin even when retracted 30 mm")
            if gaps(hi - step, x).min() > 0:
                lo = hi - step
            else:
                hi -= step
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            g = gaps(mid, x)
            lo, hi = (mid, hi) if g.min() > 0 else (lo, mid)
            x = x[g <= g.min() + 4.0 * (hi - lo)]
        return point + lo * direction

    def stepper(self, indenter_name: str, device: str = "cpu") -> IndentationStepper:
        """A pose-driven stepper for the named indenter on a warp `device`, starting from the inflated state
        (biotac frame, m). Its depth origin is the first pose stepped after each reset."""
        return IndentationStepper(self.inflated_skin(), indenter_name, None, device)

    def fluid_volume(self) -> float:
        """Fluid (liquid + air) volume in the inflated cavity (m^3): the unpressurised cavity plus what
        inflation added."""
        return self.geometry.cavity_volume_reference + self.target_volume - self._volume0

    def air_boyle(self) -> float:
        """Boyle constant (J) of the air bubble of `SkinParameters.air_volume_fraction` at the inflated state
        (0 when off; `fe.trapped_air`)."""
        self._require_reference()
        return TrappedAir.boyle(self.params.air_volume_fraction, self.fluid_volume(), self.pressure)

    def indent(
        self,
        indenter_name: str,
        point: np.ndarray,
        depth: float,
        step: float = 1e-4,
        angle_deg: float = 0.0,
        azimuth_deg: float = 0.0,
        speed: float | None = None,
        device: str = "cpu",
    ) -> Iterator[IncrementResult]:
        """Indent from first touch to `depth` (m) past it in `step` (m) increments on a warp `device`; yields
        each increment. `speed` (m/s) times the increments (t = depth / speed); a viscoelastic skin needs it."""
        if speed is not None and not speed > 0.0:
            raise ValueError(f"speed={speed} m/s must be positive")
        indenter = get_indenter(indenter_name)
        trajectory = self.plan_trajectory(indenter, point, angle_deg, azimuth_deg, depth, step)
        if speed is not None:
            trajectory = replace(trajectory, times=trajectory.depths / speed)
        stepper = IndentationStepper(self.inflated_skin(), indenter_name, trajectory.touch_point, device)
        yield from drive(stepper, trajectory)
