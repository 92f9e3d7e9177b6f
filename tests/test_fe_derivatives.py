"""Finite-difference checks of every energy's gradient and Hessian (membrane, bending, volume, contact)."""

import numpy as np
import pytest
import trimesh

from assets.indenters import get_indenter
from fe.params import ContactSettings, SkinParameters
from fe.shell import IndenterState, RigidSurface, ShellMesh, ShellSystem


def _assemble_full(system: ShellSystem, blocks: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    n = 3 * system.n_vertices
    H = np.zeros((n, n))
    for el, blk in zip(nodes, blocks, strict=True):
        dofs = (3 * el[:, None] + np.arange(3)).ravel()
        H[np.ix_(dofs, dofs)] += blk
    return H


def _rotation_about(axis: list[float], angle: float) -> np.ndarray:
    """Rotation (3,3) by `angle` (rad) about `axis` (Rodrigues)."""
    k = np.asarray(axis) / np.linalg.norm(axis)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _system(with_contact: bool) -> tuple[ShellSystem, np.ndarray]:
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=5e-3)
    rest = np.asarray(sphere.vertices)
    mesh = ShellMesh(rest, np.asarray(sphere.faces, dtype=np.int32), np.zeros(len(rest), dtype=bool))
    core = None
    if with_contact:
        inner = trimesh.creation.icosphere(subdivisions=2, radius=4.9e-3)
        core = RigidSurface(np.asarray(inner.vertices), np.asarray(inner.faces, dtype=np.int32), 0.3e-3)
    params = SkinParameters(thickness=1e-3, mu_nh=2e5, friction=0.4)
    system = ShellSystem(mesh, params, ContactSettings(penalty_stiffness=1e9, slip_length=2e-5), core)
    rng = np.random.default_rng(3)
    x = rest * 1.05 + rng.normal(scale=1e-4, size=rest.shape)
    if with_contact:
        ind = get_indenter("sphere_medium")
        # Sphere pressing on the pole from below, penetrating a few vertices.
        bottom = x[np.argmin(x[:, 2])]
        system.indenter = IndenterState(
            ind.kind,
            ind.dims,
            np.diag([1.0, -1.0, -1.0]),
            bottom + [0.0, 0.0, 2.0e-3],
            bottom + [3e-5, 0, 1.9e-3],
            0.5e-3,
            # The indenter also turned over the increment, so friction slip is seen from its body frame.
            np.diag([1.0, -1.0, -1.0]) @ _rotation_about([0.3, -0.5, 0.8], 0.05),
        )
        system.x_start = x + rng.normal(scale=2e-5, size=x.shape)
        terms = system.evaluate(x, want_hessian=False)
        system.lagged_force = 1e9 * system.vertex_area * np.maximum(-terms["indenter_gap"], 0.0)
        system.lagged_normal = terms["indenter_normal"]
        assert (terms["indenter_gap"] < 0).sum() >= 3 and (system.lagged_force > 0).any()
        assert (terms["core_gap"] < 0).sum() >= 3
    return system, x


@pytest.mark.parametrize("with_contact", [False, True])
def test_total_energy_gradient_and_hessian_match_finite_differences(with_contact: bool) -> None:
    system, x = _system(with_contact)

    def energy_and_gradient(y: np.ndarray) -> tuple[float, np.ndarray]:
        t = system.evaluate(y, want_hessian=False)
        e = t["elastic_energy"] + t["core_energy"] + t["indenter_energy"]
        return e, (t["elastic_gradient"] + t["core_gradient"] + t["indenter_gradient"]).ravel()

    t = system.evaluate(x, want_hessian=True)
    tri, stencils = system.mesh.triangles, system.bending_stencils
    H = _assemble_full(system, t["membrane_hessian"], tri) + _assemble_full(system, t["bending_hessian"], stencils)
    H += _assemble_full(system, t["contact_hessian"], np.arange(system.n_vertices)[:, None])
    _, g = energy_and_gradient(x)
    rng = np.random.default_rng(0)
    for _ in range(3):
        d = rng.normal(size=x.shape)
        h = 1e-8
        ep, gp = energy_and_gradient(x + h * d)
        em, gm = energy_and_gradient(x - h * d)
        fd_slope = (ep - em) / (2 * h)
        assert fd_slope == pytest.approx(g @ d.ravel(), rel=1e-5)
        fd_hd = (gp - gm) / (2 * h)
        assert np.linalg.norm(fd_hd - H @ d.ravel()) <= 1e-4 * np.linalg.norm(fd_hd)


def test_volume_gradient_and_hessian_match_finite_differences() -> None:
    system, x = _system(False)
    t = system.evaluate(x, want_hessian=True)
    Hv = _assemble_full(system, t["volume_hessian"], system.mesh.triangles)
    d = np.random.default_rng(1).normal(size=x.shape)
    h = 1e-8
    tp, tm = system.evaluate(x + h * d, False), system.evaluate(x - h * d, False)
    assert (tp["volume"] - tm["volume"]) / (2 * h) == pytest.approx(t["volume_gradient"].ravel() @ d.ravel(), rel=1e-7)
    fd = (tp["volume_gradient"] - tm["volume_gradient"]).ravel() / (2 * h)
    assert np.linalg.norm(fd - Hv @ d.ravel()) <= 1e-6 * np.linalg.norm(fd)


def test_membrane_energy_is_zero_at_rest_and_translation_invariant() -> None:
    system, x = _system(False)
    rest = system.evaluate(system.mesh.vertices, False)
    assert abs(rest["elastic_energy"]) < 1e-15
    moved = system.evaluate(x + [1e-3, -2e-3, 5e-4], False)
    assert moved["elastic_energy"] == pytest.approx(system.evaluate(x, False)["elastic_energy"], rel=1e-10)
    assert np.allclose(moved["elastic_gradient"].sum(axis=0), 0.0, atol=1e-12)
