"""The TIN surface: exact on planes inside the hull, nearest vertex outside; the CHM layers' TINs."""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

from terrasift.workers.chm import _triangulate
from terrasift.workers.surface import TinSurface


def test_tin_of_a_plane_is_the_plane_inside_and_nearest_vertex_outside():
    rng = np.random.default_rng(8)
    xy = rng.uniform(0, 200, (20_000, 2)) + [5e5, 5.4e6]
    plane = lambda x, y: 0.3 * (x - 5e5) - 0.1 * (y - 5.4e6) + 7.0  # noqa: E731
    # hull corners, so every query in [1, 199]² lies inside the TIN
    corners = np.array([[0, 0], [200, 0], [0, 200], [200, 200]]) + [5e5, 5.4e6]
    xy = np.vstack([xy, corners])
    surface = TinSurface(np.column_stack([xy, plane(xy[:, 0], xy[:, 1])]))
    q = rng.uniform(1, 199, (50_000, 2)) + [5e5, 5.4e6]
    assert np.abs(surface(q[:, 0], q[:, 1]) - plane(q[:, 0], q[:, 1])).max() < 1e-6
    gx, gy = np.meshgrid(np.arange(1, 199, 0.5) + 5e5, np.arange(1, 199, 0.5) + 5.4e6)
    assert np.abs(surface(gx, gy) - plane(gx, gy)).max() < 1e-6
    assert surface(gx, gy).shape == gx.shape
    # outside the hull: the nearest vertex's height
    assert np.isclose(
        surface(np.array([5e5 + 210.0]), np.array([5.4e6 + 205.0]))[0],
        plane(5e5 + 200, 5.4e6 + 200),
    )


def test_coincident_points_keep_the_lowest_and_few_points_give_the_nearest():
    xyz = np.array([[0.0, 0.0, 5.0], [0.0004, 0.0, 3.0], [10.0, 0.0, 1.0], [0.0, 10.0, 2.0]])
    surface = TinSurface(xyz)
    # the two points 0.4 mm apart are one vertex at the lower height
    assert np.isclose(surface(np.array([0.0004]), np.array([0.0]))[0], 3.0)
    assert np.isclose(surface(np.array([5.0]), np.array([0.0]))[0], 2.0, atol=1e-3)  # (3 + 1) / 2
    two = TinSurface(np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 4.0]]))
    assert np.allclose(two(np.array([1.0, 9.0]), np.array([0.0, 0.0])), [1.0, 4.0])
    collinear = TinSurface(np.array([[0.0, 0.0, 1.0], [5.0, 0.0, 2.0], [10.0, 0.0, 4.0]]))
    assert np.allclose(collinear(np.array([4.0]), np.array([1.0])), [2.0])


def test_chm_layers_get_delaunay_triangles_numbered_as_the_input():
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 200, (5000, 2))
    xy = xy[np.argsort(xy[:, 0])]  # cloud order: sorted by x
    tri, simplices = _triangulate(xy)
    reference = Delaunay(xy)
    assert {tuple(t) for t in np.sort(simplices, axis=1)} == {
        tuple(t) for t in np.sort(reference.simplices, axis=1)
    }
    # find_simplex answers rows of ``simplices``: each query lies in its triangle
    q = rng.uniform(10, 190, (2000, 2))
    s = tri.find_simplex(q)
    assert (s >= 0).all()
    a, b, c = (xy[simplices[s, k]] for k in range(3))

    def cross(u, v):
        return u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]

    sides = np.column_stack([cross(b - a, q - a), cross(c - b, q - b), cross(a - c, q - c)])
    assert ((sides >= -1e-9).all(axis=1) | (sides <= 1e-9).all(axis=1)).all()
