"""The contact area an increment reports (`fe.shell.pressed_areas`): lumped vertex areas of the pressed vertices,
checked on a flat regular grid whose areas are known in closed form."""

import numpy as np
import pytest

from fe.shell import lumped_areas, pressed_areas

H = 1e-3  # m, grid spacing
N = 6  # vertices a side


def _grid() -> tuple[np.ndarray, np.ndarray]:
    """A flat N x N vertex grid of spacing H, each square cut into two triangles along one diagonal direction."""
    i, j = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    vertices = np.column_stack([H * i.ravel(), H * j.ravel(), np.zeros(N * N)])
    v = lambda a, b: a * N + b  # noqa: E731
    triangles = [
        tri
        for a in range(N - 1)
        for b in range(N - 1)
        for tri in ((v(a, b), v(a + 1, b), v(a + 1, b + 1)), (v(a, b), v(a + 1, b + 1), v(a, b + 1)))
    ]
    return vertices, np.array(triangles)


def test_pressed_areas_are_the_lumped_areas_of_the_pressed_vertices() -> None:
    vertices, triangles = _grid()
    meshes = np.stack([vertices, vertices * [2.0, 1.0, 1.0], vertices])  # the second stretched 2x along x
    pressed = np.zeros((3, N * N), dtype=bool)
    pressed[0] = True  # the whole sheet: its area
    pressed[1, 2 * N + 3] = True  # one interior vertex: six triangles of (2H)H/2, a third each
    areas = pressed_areas(meshes, pressed, triangles)
    assert areas == pytest.approx([(N - 1) ** 2 * H**2, 2.0 * H**2, 0.0], rel=1e-12, abs=1e-20)
    assert lumped_areas(vertices, triangles)[2 * N + 3] == pytest.approx(H**2, rel=1e-12)
    corner = np.zeros((1, N * N), dtype=bool)
    corner[0, N - 1] = True  # a corner of one triangle only: a third of H^2 / 2
    assert pressed_areas(vertices[None], corner, triangles) == pytest.approx([H**2 / 6.0], rel=1e-12)
