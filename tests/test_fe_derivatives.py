"""Finite-difference checks of every energy's gradient and Hessian (membrane, bending, volume, contact) as the FE
engine (`fe.batched.BatchedShell`) evaluates them, with two systems per batch so that rows cannot mix."""

import numpy as np
import pytest
import trimesh
import warp as wp

from assets.indenters import get_indenter
from fe.batched import BatchedShell, InflatedSkin
from fe.bending import build_stencils
from fe.params import ContactSettings, SkinParameters

B = 2
"""Systems per batch: each row is checked against finite differences of its own energy."""


def _assemble_full(n_vertices: int, blocks: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Dense (3V,3V) matrix from element blocks over `nodes` (repeated nodes accumulate)."""
    H = np.zeros((3 * n_vertices, 3 * n_vertices))
    for el, blk in zip(nodes, blocks, strict=True):
        dofs = (3 * el[:, None] + np.arange(3)).ravel()
        np.add.at(H, np.ix_(dofs, dofs), blk)
    return H


def _rotation_about(axis: list[float], angle: float) -> np.ndarray:
    """Rotation (3,3) by `angle` (rad) about `axis` (Rodrigues)."""
    k = np.asarray(axis) / np.linalg.norm(axis)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _enclosed_volume(x: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume (m^3) of a closed outward-oriented triangle mesh (divergence theorem), in numpy."""
    p0, p1, p2 = (x[triangles[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0)


def _host(a: wp.array) -> np.ndarray:
    """A copy of a warp array (on the CPU `.numpy()` is a view the next evaluation overwrites)."""
    return a.numpy().copy()


def _warp(x: np.ndarray) -> wp.array:
    return wp.array(np.asarray(x, dtype=np.float64), dtype=wp.vec3d, device="cpu")


class _Probe:
    """A BatchedShell of B icosphere skins (5 mm, 1 mm thick) with positions x (B,V,3), optionally pressed by a
    frictional sphere indenter from below and onto a rigid inner core."""

    def __init__(self, with_contact: bool, fixed: np.ndarray | None = None) -> None:
        sphere = trimesh.creation.icosphere(subdivisions=1, radius=5e-3)
        rest = np.asarray(sphere.vertices)
        self.triangles = np.asarray(sphere.faces, dtype=np.int32)
        core = None
        if with_contact:
            inner = trimesh.creation.icosphere(subdivisions=2, radius=4.9e-3)
            core = (np.asarray(inner.vertices), np.asarray(inner.faces, dtype=np.int32), 0.3e-3)
        params = SkinParameters(thickness=1e-3, mu_nh=2e5, friction=0.4)
        fixed = np.zeros(len(rest), dtype=bool) if fixed is None else fixed
        contact = ContactSettings(penalty_stiffness=1e9, slip_length=2e-5)
        self.skin = InflatedSkin.at_rest(rest, self.triangles, fixed, params, contact, core=core)
        ind = get_indenter("sphere_medium")
        self.shell = BatchedShell(self.skin, [(ind.kind, ind.dims)] * B, device="cpu")
        self.rest, self.n_vertices = rest, len(rest)
        rng = np.random.default_rng(3)
        self.x = np.stack([rest * (1.05 + 0.01 * b) + rng.normal(scale=1e-4, size=rest.shape) for b in range(B)])
        if with_contact:
            self._press(rng)

    def _press(self, rng: np.random.Generator) -> None:
        """Sphere pressing on each system's pole from below (it also moved and turned over the increment, so
        friction slip is seen from its body frame), penetrating a few vertices; lagged friction forces set."""
        flip = np.diag([1.0, -1.0, -1.0])
        bottom = np.stack([xb[np.argmin(xb[:, 2])] for xb in self.x])
        rot = np.stack([flip] * B)
        rot_start = np.stack([flip @ _rotation_about([0.3, -0.5, 0.8], 0.05 * (b + 1)) for b in range(B)])
        self.shell.set_poses(rot, bottom + [0.0, 0.0, 2.0e-3], rot_start, bottom + [3e-5, 0.0, 1.9e-3])
        self.shell.x_start.assign(self.x + rng.normal(scale=2e-5, size=self.x.shape))
        self.evaluate(self.x, want_hessian=False)
        gap = self.shell.buf["indenter_gap"].numpy()
        lagged = 1e9 * self.shell.vertex_area * np.maximum(-gap, 0.0)
        self.shell.lagged_force.assign(lagged)
        self.shell.lagged_normal.assign(self.shell.buf["indenter_normal"].numpy())
        assert ((gap < 0).sum(axis=1) >= 3).all() and (lagged > 0).any(axis=1).all()
        face_gap = self.shell.buf["indenter_face_gap"].numpy()
        assert ((face_gap < 0).sum(axis=1) >= 3).all()  # the surface contact acts on several triangles
        assert ((self.shell.buf["core_gap"].numpy() < 0).sum(axis=1) >= 3).all()

    def evaluate(self, x: np.ndarray, want_hessian: bool, pressure: np.ndarray | None = None):
        pressure = np.zeros(B) if pressure is None else pressure
        return self.shell.evaluate(_warp(x), want_hessian, pressure)

    def energy_and_gradient(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Total potential energy (B,) J (membrane + bending + core + indenter, summed here from the per-element
        buffers) and its gradient (B,3V) N (sum of the engine's three gradient buffers)."""
        self.evaluate(x, want_hessian=False)
        buf = self.shell.buf
        terms = ("membrane_energy", "bending_energy", "core_energy", "indenter_energy", "indenter_face_energy")
        energy = sum(buf[name].numpy().sum(axis=1) for name in terms)
        return energy, self.shell.gradients.numpy().sum(axis=0).reshape(B, -1)

    def hessians(self, x: np.ndarray) -> list[np.ndarray]:
        """Dense Hessian (3V,3V) of each system, assembled here from the engine's element blocks."""
        self.evaluate(x, want_hessian=True)
        buf, V = self.shell.buf, self.n_vertices
        stencils = build_stencils(self.triangles)[0]
        assert self.shell.n_bending == len(stencils)
        contact = buf["core_hessian"].numpy() + buf["indenter_hessian"].numpy()
        out = []
        for b in range(B):
            H = _assemble_full(V, buf["membrane_hessian"].numpy()[b], self.triangles)
            H += _assemble_full(V, buf["bending_hessian"].numpy()[b], stencils)
            H += _assemble_full(V, contact[b], np.arange(V)[:, None])
            out.append(H)
        return out


@pytest.mark.parametrize("with_contact", [False, True])
def test_total_energy_gradient_and_hessian_match_finite_differences(with_contact: bool) -> None:
    probe = _Probe(with_contact)
    x = probe.x
    Hs = probe.hessians(x)
    e, g = probe.energy_and_gradient(x)
    lin = probe.evaluate(x, want_hessian=False)  # no trapped air: the engine's total is the plain sum
    assert lin.energy == pytest.approx(e, rel=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(3):
        d = rng.normal(size=x.shape)
        h = 1e-8
        ep, gp = probe.energy_and_gradient(x + h * d)
        em, gm = probe.energy_and_gradient(x - h * d)
        for b in range(B):
            fd_slope = (ep[b] - em[b]) / (2 * h)
            assert fd_slope == pytest.approx(g[b] @ d[b].ravel(), rel=1e-5)
            fd_hd = (gp[b] - gm[b]) / (2 * h)
            assert np.linalg.norm(fd_hd - Hs[b] @ d[b].ravel()) <= 1e-4 * np.linalg.norm(fd_hd)


def test_volume_gradient_and_hessian_match_finite_differences() -> None:
    probe = _Probe(False)
    x, V = probe.x, probe.n_vertices
    lin = probe.evaluate(x, want_hessian=True)
    for b in range(B):  # against an independent divergence-theorem volume, and the per-triangle buffer
        assert lin.volume[b] == pytest.approx(_enclosed_volume(x[b], probe.triangles), rel=1e-12)
    assert np.allclose(probe.shell.buf["volume"].numpy().sum(axis=1), lin.volume, rtol=1e-12, atol=0)
    grad = _host(probe.shell.buf["volume_gradient"]).reshape(B, -1)
    Hv = [_assemble_full(V, probe.shell.buf["volume_hessian"].numpy()[b], probe.triangles) for b in range(B)]
    d = np.random.default_rng(1).normal(size=x.shape)
    h = 1e-8
    for b in range(B):
        fd = _enclosed_volume(x[b] + h * d[b], probe.triangles) - _enclosed_volume(x[b] - h * d[b], probe.triangles)
        assert fd / (2 * h) == pytest.approx(grad[b] @ d[b].ravel(), rel=1e-7)
    lp = probe.evaluate(x + h * d, False)
    gp = _host(probe.shell.buf["volume_gradient"]).reshape(B, -1)
    lm = probe.evaluate(x - h * d, False)
    gm = _host(probe.shell.buf["volume_gradient"]).reshape(B, -1)
    for b in range(B):
        assert (lp.volume[b] - lm.volume[b]) / (2 * h) == pytest.approx(grad[b] @ d[b].ravel(), rel=1e-7)
        fd = (gp[b] - gm[b]) / (2 * h)
        assert np.linalg.norm(fd - Hv[b] @ d[b].ravel()) <= 1e-6 * np.linalg.norm(fd)


def test_residual_is_free_energy_gradient_minus_pressure_times_volume_gradient() -> None:
    """`BatchedShell.residual` = grad E - p grad V on free DOFs, 0 on held ones; grad V from finite differences
    of the numpy volume, grad E from finite differences of the energy."""
    fixed = np.zeros(42, dtype=bool)
    fixed[[0, 5, 17]] = True
    probe = _Probe(False, fixed=fixed)
    x, V = probe.x, probe.n_vertices
    pressure = np.array([1.5e3, -4e2])
    probe.evaluate(x, want_hessian=False, pressure=pressure)
    residual = _host(probe.shell.residual)
    h = 1e-8
    grad_v, grad_e = np.zeros((B, V, 3)), np.zeros((B, V, 3))
    for v in range(V):
        for k in range(3):
            xp, xm = x.copy(), x.copy()
            xp[:, v, k] += h
            xm[:, v, k] -= h
            for b in range(B):
                vp, vm = _enclosed_volume(xp[b], probe.triangles), _enclosed_volume(xm[b], probe.triangles)
                grad_v[b, v, k] = (vp - vm) / (2 * h)
            grad_e[:, v, k] = (probe.energy_and_gradient(xp)[0] - probe.energy_and_gradient(xm)[0]) / (2 * h)
    for b in range(B):
        expected = grad_e[b] - pressure[b] * grad_v[b]
        expected[fixed] = 0.0
        assert np.abs(residual[b][fixed]).max() == 0.0
        assert np.linalg.norm(residual[b] - expected) <= 1e-5 * np.linalg.norm(expected)


def test_membrane_energy_is_zero_at_rest_and_translation_invariant() -> None:
    probe = _Probe(False)
    x = probe.x
    rest_energy, _ = probe.energy_and_gradient(np.stack([probe.rest] * B))
    assert np.abs(rest_energy).max() < 1e-15
    moved_energy, moved_gradient = probe.energy_and_gradient(x + [1e-3, -2e-3, 5e-4])
    energy, _ = probe.energy_and_gradient(x)
    assert moved_energy == pytest.approx(energy, rel=1e-10)
    assert np.allclose(moved_gradient.reshape(B, -1, 3).sum(axis=1), 0.0, atol=1e-12)
