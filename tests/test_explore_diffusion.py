"""Diffusion on the cloud: the spectral heat kernel (eq. 19) against the analytic Neumann heat
kernel of a square, the implicit baseline against the screened-Poisson Green's function,
conservation of ∫u, and the explorer's reduced carry-over arithmetic against the full operator."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import jittered_square
from scipy.special import k0

from tergodic_cli.basis import compute_basis
from tergodic_cli.capture.synthetic import generate_synthetic
from tergodic_cli.explore import ExploreConfig, Explorer
from tergodic_cli.explore import kernels as K
from tergodic_cli.explore.diffusion import ImplicitDiffusion, time_step

SIDE = 0.1  # metres


class SpectralDiffusion:
    """e^{-δt L} in the truncated eigenbasis Φ (n, nK), eigenvalues λ (nK,): eq. 19 on full fields, the reference."""

    def __init__(self, evecs, evals, mass, dt):
        self.evecs, self.evals, self.mass = evecs, evals, mass
        self.decay = np.exp(-evals * float(dt))

    def apply(self, u):
        return self.evecs @ (self.decay * (self.evecs.T @ (self.mass * u)))

    def kernel(self, i):
        """Heat kernel k_δt(·, x_i): the field from a unit mass at point i."""
        return self.evecs @ (self.decay * self.evecs[i])


@pytest.fixture(scope="module")
def square():
    pts = jittered_square(40, SIDE, seed=0)  # 1600 points, h ≈ 2.4 mm
    return pts, compute_basis(pts, 120, 30)


def _neumann_heat_kernel(t, x, y):
    """Heat kernel of the Neumann square [0, SIDE]² by the method of images (nearest images)."""
    total = np.zeros(len(x))
    for sx in (-y[0], y[0], 2 * SIDE - y[0]):
        for sy in (-y[1], y[1], 2 * SIDE - y[1]):
            r2 = (x[:, 0] - sx) ** 2 + (x[:, 1] - sy) ** 2
            total += np.exp(-r2 / (4 * t)) / (4 * np.pi * t)
    return total


def _centre(pts):
    return int(np.argmin(((pts[:, :2] - SIDE / 2) ** 2).sum(1)))


def test_spectral_heat_kernel_matches_the_analytic_neumann_kernel_on_a_flat_patch(square):
    pts, basis = square
    i = _centre(pts)
    t = 4e-5  # m²: kernel width √(2t) ≈ 9 mm, small against the 100 mm patch
    k = SpectralDiffusion(basis.evecs, basis.evals, basis.mass, t).kernel(i)
    exact = _neumann_heat_kernel(t, pts, pts[i])
    assert np.abs(k - exact).max() < 0.06 * exact.max()
    # The comparison has teeth: twice the time is far off.
    assert np.abs(k - _neumann_heat_kernel(2 * t, pts, pts[i])).max() > 0.3 * exact.max()


def test_implicit_step_matches_the_screened_poisson_green_function(square):
    # (M + t L)⁻¹ M δ solves u - tΔu = δ: in the plane u = K0(r/√t) / (2π t).
    pts, basis = square
    i = _centre(pts)
    t = 2e-5
    delta = np.zeros(len(pts))
    delta[i] = 1.0 / basis.mass[i]
    u = ImplicitDiffusion(basis.L, basis.mass, t).apply(delta)
    r = np.linalg.norm(pts - pts[i], axis=1)
    ring = (r > 3 * basis.h) & (r < 4 * np.sqrt(t))
    g = k0(r[ring] / np.sqrt(t)) / (2 * np.pi * t)
    assert np.abs(u[ring] - g).max() < 0.08 * g.max()


@pytest.fixture(scope="module")
def bowl():
    cloud = generate_synthetic("bowl", "X", seed=3, spacing=0.004)
    return cloud, compute_basis(cloud.points, 60, 30)


def test_diffusion_conserves_the_integral_neumann(bowl):
    cloud, basis = bowl
    u = np.random.default_rng(0).uniform(0, 1, len(basis.mass))
    total = basis.mass @ u
    dt = time_step(10)
    spec = SpectralDiffusion(basis.evecs, basis.evals, basis.mass, dt)
    imp = ImplicitDiffusion(basis.L, basis.mass, dt)
    v, w = u.copy(), u.copy()
    for _ in range(20):
        v, w = spec.apply(v), imp.apply(w)
    np.testing.assert_allclose(basis.mass @ v, total, rtol=1e-10)
    np.testing.assert_allclose(basis.mass @ w, total, rtol=1e-10)
    # ... while the field itself does change (it diffuses).
    assert np.abs(v - u).max() > 0.1


@pytest.mark.parametrize("integrator", ["spectral", "implicit"])
@pytest.mark.parametrize("diffusion", ["carry", "source"])
def test_explorer_heat_integral_grows_by_the_injected_unit_mass(bowl, integrator, diffusion):
    # carry: u₀ = p̄ (unit mass) and every step adds s/∫s (unit mass) while diffusion conserves,
    # so ∫u = 1 + k after k steps; source: u = e^{-δtL} s/∫s has unit mass at every step.
    cloud, basis = bowl
    target = cloud.mask.astype(float)
    cfg = ExploreConfig(nk=60, agent_radius=0.012, diffusion=diffusion, integrator=integrator)
    ex = Explorer(basis, target, cfg, basis.points[np.flatnonzero(target)[:1]])
    for k in range(1, 8):
        ex.step()
        expected = 1.0 + k if diffusion == "carry" else 1.0
        np.testing.assert_allclose(basis.mass @ ex.heat, expected, rtol=1e-9)


@pytest.mark.parametrize("integrator", ["spectral", "resolvent"])
def test_explorer_reduced_spectral_carry_equals_the_full_operator(bowl, integrator):
    # The explorer keeps spectral coefficients and the target-only source; the full recursion
    # u_t = Φ f(λδt) Φᵀ M u_{t-1} + s̄_t from u₀ = p̄ must give the same field, with
    # f = e^{-x} (eq. 19) or 1/(1 + x) (eq. 4, the spectral form of (M + δt L)⁻¹ M).
    cloud, basis = bowl
    target = cloud.mask.astype(float)
    ex = Explorer(basis, target, ExploreConfig(nk=60, agent_radius=0.012, integrator=integrator), basis.points[:1])
    dt = time_step(10)
    spec = SpectralDiffusion(basis.evecs, basis.evals, basis.mass, dt)
    if integrator == "resolvent":
        spec.decay = 1.0 / (1.0 + basis.evals * dt)
    u = target / (basis.mass @ target)
    for _ in range(6):
        ex.step()
        s = ex.source
        u = spec.apply(u) + s / (basis.mass @ s)
        np.testing.assert_allclose(ex.heat, u, rtol=1e-9, atol=1e-9 * np.abs(u).max())


def test_spectral_resolvent_approaches_the_sparse_implicit_step(bowl):
    # With every eigenpair the two are the same operator; with 60 of them the smooth part agrees.
    cloud, basis = bowl
    dt = 10 * basis.h**2  # the operators' comparison, at the sheet's own scale
    u = np.exp(-((basis.points - basis.points[0]) ** 2).sum(1) / 0.02**2)  # smooth, 2 cm wide
    exact = ImplicitDiffusion(basis.L, basis.mass, dt).apply(u)
    coef = basis.evecs.T @ (basis.mass * u)
    approx = basis.evecs @ (coef / (1.0 + basis.evals * dt))
    heat = basis.evecs @ (coef * np.exp(-basis.evals * dt))  # eq. 19: a different operator
    err = np.abs(approx - exact).max()
    assert err < 0.05 * exact.max()
    assert err < 0.5 * np.abs(heat - exact).max()


def test_alpha_schedule_switches_the_time_step(bowl):
    cloud, basis = bowl
    target = cloud.mask.astype(float)
    ex = Explorer(basis, target, ExploreConfig(nk=60, agent_radius=0.012, alpha="50:10@3", integrator="spectral"), basis.points[:1])
    seen = []
    for _ in range(5):
        seen.append(ex.alpha)
        ex.step()
    assert seen == [50.0, 50.0, 50.0, 10.0, 10.0]
    np.testing.assert_allclose(ex._sp[K.SP_DECAY], np.exp(-basis.evals * time_step(10)))
