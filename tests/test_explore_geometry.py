"""The CGA plane/sphere fit (eqs. 23-26), projection (27), normal line and tangent plane (28-29),
and the weighted cubic gradient (32-33), against analytic surfaces and polynomials."""

from __future__ import annotations

import numpy as np
import pytest

from reference_geometry import (
    conformal_rows,
    fit_primitive,
    normal_line,
    orient,
    project_onto,
    tangent_basis,
    tangent_distances,
)
from reference_geometry import cubic_gradient, cubic_value, fit_cubic


def _cap_samples(centre, radius, axis, half_angle, k, rng):
    """k points on the spherical cap around ``axis`` (unit) with the given half angle."""
    t1, t2 = tangent_basis(axis)
    cos_t = rng.uniform(np.cos(half_angle), 1.0, k)
    sin_t = np.sqrt(1 - cos_t**2)
    phi = rng.uniform(0, 2 * np.pi, k)
    dirs = cos_t[:, None] * axis + sin_t[:, None] * (np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2)
    return centre + radius * dirs


def _plane_samples(point, normal, half_width, k, rng):
    t1, t2 = tangent_basis(normal)
    uv = rng.uniform(-half_width, half_width, (k, 2))
    return point + uv[:, :1] * t1 + uv[:, 1:] * t2


def test_conformal_rows_give_the_algebraic_distance_to_a_sphere():
    # P·X* = -½(|x - c|² - r²) for the dual sphere X* = c + ½(|c|² - r²) e∞ + e0 (eq. 25 rows).
    c, r = np.array([0.1, -0.2, 0.3]), 0.05
    v = np.concatenate([c, [0.5 * (c @ c - r * r)], [1.0]])
    x = np.random.default_rng(0).normal(size=(7, 3)) * 0.1
    np.testing.assert_allclose(conformal_rows(x) @ v, -0.5 * (((x - c) ** 2).sum(1) - r * r), atol=1e-15)


@pytest.mark.parametrize("seed", range(5))
def test_sphere_fit_recovers_centre_and_radius_from_noisy_samples(seed):
    rng = np.random.default_rng(seed)
    centre, radius = np.array([0.12, -0.05, 0.31]), 0.04
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    pts = _cap_samples(centre, radius, axis, np.deg2rad(50), 60, rng)
    pts += rng.normal(scale=2e-5, size=pts.shape)  # 20 µm noise, 0.05 % of the radius
    prim = fit_primitive(pts)
    assert prim.kind == "sphere"
    assert abs(prim.radius - radius) < 0.01 * radius
    assert np.linalg.norm(prim.centre - centre) < 0.01 * radius


def test_sphere_fit_is_exact_without_noise():
    rng = np.random.default_rng(1)
    centre, radius = np.array([-0.3, 0.2, 0.05]), 0.02
    pts = _cap_samples(centre, radius, np.array([0.0, 0.0, 1.0]), np.deg2rad(30), 20, rng)
    prim = fit_primitive(pts)
    assert prim.kind == "sphere"
    assert abs(prim.radius - radius) < 1e-9
    np.testing.assert_allclose(prim.centre, centre, atol=1e-9)


@pytest.mark.parametrize("normal", [(0, 0, 1), (1, 0, 0), (0, 1, 0), (0.6, 0.0, 0.8), (0.3, -0.5, 0.1)],
                         ids=["floor", "vertical-x", "vertical-y", "tilted", "oblique"])
def test_plane_fit_recovers_the_normal_from_noisy_samples_including_vertical_walls(normal):
    rng = np.random.default_rng(2)
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    point = np.array([0.2, 0.1, 0.05])
    pts = _plane_samples(point, n, 0.006, 20, rng) + rng.normal(scale=3e-5, size=(20, 3))
    prim = fit_primitive(pts)
    x = point + 0.003 * n + 0.001 * tangent_basis(n)[0]
    xp, nn = project_onto(prim, x)
    # A plane, or a sphere so large it is the plane: the normal at the projection is what matters.
    assert abs(nn @ n) > np.cos(np.deg2rad(1.0))
    assert abs((xp - point) @ n) < 1e-4  # on the plane to within the noise


@pytest.mark.parametrize("normal", [(1, 0, 0), (0, 0, 1), (0, 0.6, 0.8)])
def test_exactly_flat_patch_is_a_plane_even_when_vertical(normal):
    # A height field z = f(x, y) cannot represent x = const; the CGA fit must.
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    pts = _plane_samples(np.array([0.3, -0.1, 0.2]), n, 0.005, 20, np.random.default_rng(3))
    prim = fit_primitive(pts)
    assert prim.kind == "plane"
    assert abs(abs(prim.normal @ n) - 1) < 1e-12
    assert np.abs(pts @ prim.normal - prim.offset).max() < 1e-12


def test_projection_onto_sphere_and_plane():
    from reference_geometry import Primitive

    sph = Primitive("sphere", centre=np.array([0.0, 0.0, 0.0]), radius=0.05)
    x = np.array([0.03, 0.04, 0.12])
    xp, n = project_onto(sph, x)
    np.testing.assert_allclose(np.linalg.norm(xp), 0.05, atol=1e-15)
    np.testing.assert_allclose(n, x / np.linalg.norm(x), atol=1e-15)
    pl = Primitive("plane", normal=np.array([1.0, 0.0, 0.0]), offset=0.2)
    xp, n = project_onto(pl, np.array([0.5, 0.1, -0.3]))
    np.testing.assert_allclose(xp, [0.2, 0.1, -0.3], atol=1e-15)
    with pytest.raises(ValueError):
        project_onto(sph, np.zeros(3))


def test_normal_line_tangent_frame_and_tangent_distances():
    n = np.array([0.0, 0.6, 0.8])
    t1, t2 = tangent_basis(n)
    frame = np.column_stack([t1, t2, n])
    np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-15)
    assert np.linalg.det(frame) > 0
    p = np.array([0.1, 0.2, 0.3])
    line = normal_line(p, n, np.array([-1.0, 0.0, 2.0]))
    np.testing.assert_allclose(line[2] - p, 2 * n, atol=1e-15)
    # Tangent-plane distance (eq. 31) ignores the offset along the normal.
    q = p + 0.003 * t1 + 0.004 * t2 + 0.05 * n
    np.testing.assert_allclose(tangent_distances(q[None], p, n), [0.005], atol=1e-15)
    assert orient(-n, n) @ n > 0


# ---------------------------------------------------------------------------------------- gradient
def _known_cubic():
    # Coefficients sized so every term matters on a 6 mm patch (values and slopes O(1)).
    return np.array([0.3, 2.0, -1.5, 40.0, -25.0, 10.0, 900.0, -700.0, 500.0, -300.0])


def _analytic_gradient(c, uv):
    u, v = uv[:, 0], uv[:, 1]
    du = c[1] + 2 * c[3] * u + c[4] * v + 3 * c[6] * u**2 + 2 * c[7] * u * v + c[8] * v**2
    dv = c[2] + c[4] * u + 2 * c[5] * v + c[7] * u**2 + 2 * c[8] * u * v + 3 * c[9] * v**2
    return np.column_stack([du, dv])


def test_weighted_cubic_fit_recovers_the_gradient_of_a_known_cubic():
    rng = np.random.default_rng(4)
    c = _known_cubic()
    uv = rng.uniform(-0.006, 0.006, (20, 2))
    values = cubic_value(c, uv)
    w = np.exp(-(133.0**2) * (uv**2).sum(1))
    coef = fit_cubic(uv, values, w)
    probe = np.vstack([[0.0, 0.0], rng.uniform(-0.005, 0.005, (8, 2))])
    expected = _analytic_gradient(c, probe)
    got = cubic_gradient(coef, probe)
    assert np.abs(got - expected).max() < 1e-6
    # At the origin (the agent's projected position) the gradient is the linear coefficients.
    np.testing.assert_allclose(got[0], c[1:3], atol=1e-6)


def test_cubic_gradient_is_right_in_the_v_direction_too():
    # Only mixed terms: u²v and uv². ∂/∂v = u² + 2uv, ∂/∂u = 2uv + v² (the published code's
    # v-derivative drops and misweights exactly these terms).
    c = np.zeros(10)
    c[7], c[8] = 1.0, 1.0
    uv = np.random.default_rng(5).uniform(-0.004, 0.004, (20, 2))
    coef = fit_cubic(uv, cubic_value(c, uv))
    p = np.array([[0.002, -0.001]])
    np.testing.assert_allclose(cubic_gradient(coef, p), [[2 * 0.002 * -0.001 + 0.001**2, 0.002**2 + 2 * 0.002 * -0.001]],
                               atol=1e-9)


def test_cubic_fit_degrades_gracefully_with_degenerate_neighbours():
    # Collinear samples cannot determine a 2-D cubic: a finite minimum-norm answer, no crash.
    u = np.linspace(-0.005, 0.005, 20)
    uv = np.column_stack([u, np.zeros_like(u)])
    coef = fit_cubic(uv, 3.0 * u)
    assert np.all(np.isfinite(coef))
    np.testing.assert_allclose(cubic_gradient(coef, np.zeros((1, 2)))[0, 0], 3.0, rtol=1e-6)
