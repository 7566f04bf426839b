"""Surface sampling for the distance field: cost follows area, not triangle shape.

Oracle: points drawn uniformly on the surface by trimesh's own sampler (area-weighted, shares no
code with ctrplan) must each lie within the returned covering radius of a sample (nearest
neighbour by scipy's KD-tree). The sample count of a CAD-style cylinder wall (long thin
triangles) stays proportional to its area: this is what bounds field preparation's memory and
time (the timing itself is in benchmarks/bench_field_prep.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ctrplan.collision.field import surface_samples


def _covered(mesh, samples, rho, n=20000, seed=0):
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    d, _ = cKDTree(samples).query(pts)
    return float(d.max()), rho


def test_cylinder_wall_samples_follow_area():
    cyl = trimesh.creation.cylinder(radius=20.0, height=400.0, sections=64)
    assert len(cyl.faces) == 256
    max_edge = 0.25                                  # h / 2 at the default h = 0.5 mm
    sv, e = surface_samples(np.asarray(cyl.vertices, float), np.asarray(cyl.faces), max_edge)
    # per unit area a square grid of spacing max_edge needs 1 / max_edge^2 points; allow the
    # lattice on the (well-shaped) caps and the edge crossings on top: at most 2x
    area = float(cyl.area)
    assert len(sv) <= 2.0 * area / max_edge**2, (len(sv), area)
    assert len(sv) < 2_000_000                       # the longest-edge lattice needed ~145 M
    assert e <= math.sqrt(2.0) * max_edge + 1e-12
    worst, rho = _covered(cyl, sv, e / math.sqrt(3.0))
    assert worst <= rho + 1e-9, (worst, rho)


@pytest.mark.parametrize("aspect", [1.0, 30.0, 400.0])
def test_single_triangles_covered_and_count_scales_with_area(aspect):
    rng = np.random.default_rng(int(aspect))
    # a triangle of area 200 mm^2 with the given aspect ratio, randomly rotated in space
    base = math.sqrt(400.0 * aspect)
    height = 400.0 / base
    tri2 = np.array([[0.0, 0.0, 0.0], [base, 0.0, 0.0], [0.3 * base, height, 0.0]])
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    v = tri2 @ q.T + rng.normal(size=3) * 10
    f = np.array([[0, 1, 2]])
    sv, e = surface_samples(v, f, 0.25)
    mesh = trimesh.Trimesh(v, f, process=False)
    worst, rho = _covered(mesh, sv, e / math.sqrt(3.0), n=5000)
    assert worst <= rho + 1e-9, (aspect, worst, rho)
    # all samples lie on the triangle's plane and inside its bounding box
    normal = np.cross(v[1] - v[0], v[2] - v[0])
    normal /= np.linalg.norm(normal)
    assert np.abs((sv - v[0]) @ normal).max() < 1e-9
    assert len(sv) <= 2.0 * 200.0 / 0.25**2 + 4 * (2 * base + height) / 0.25 + 3, (aspect, len(sv))


def test_degenerate_triangle_is_covered_as_a_segment():
    v = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    sv, e = surface_samples(v, np.array([[0, 1, 2]]), 0.25)
    assert np.all(np.isfinite(sv))
    x = np.sort(sv[:, 0])
    assert x[0] == 0.0 and x[-1] == 100.0 and np.diff(x).max() <= 0.25 + 1e-12
