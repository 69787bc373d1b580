"""Sampled, limb-darkened solar disk and direct irradiance."""

import numpy as np
import pytest

from crater_thermal import illumination as il
from crater_thermal.constants import AU, SUN_RADIUS
from crater_thermal.errors import ConfigError

LAWS = sorted(il.LIMB_DARKENING_LAWS)
ALPHA = np.arcsin(SUN_RADIUS / AU)  # angular radius of the Sun at 1 au [rad]


class _Facets:
    """Test double of geometry.Mesh: facets at the origin with given normals."""

    def __init__(self, normals):
        self.normals = np.atleast_2d(np.asarray(normals, float))
        self.vertices = np.array([[0.0, 0.0, -1.0]])  # lowest point; origins at z=0 are "above all"


class _NoOcclusion:
    def facet_origins(self, idx):
        return np.zeros((len(idx), 3))

    def occluded(self, o, d):
        return np.zeros(len(o), bool)


class _HorizonPlane(_NoOcclusion):
    """Terrain: everything below the horizontal plane through the facet is opaque."""

    def occluded(self, o, d):
        return d[:, 2] < 0.0


def _exact_flat_horizon_flux(law, n_mu=400, n_phi=2000):
    """Fraction of S on a horizontal facet with the Sun's centre on the horizon.

    ``int_{upper half-disk} I(mu) sin(alpha y) dA / int_disk I dA`` by a fine polar
    quadrature (Gauss-Legendre in mu, midpoint in azimuth), independent of sun_disk.
    """
    coeffs = il.law_coefficients(law)
    x, w = np.polynomial.legendre.leggauss(n_mu)
    mu, wm = 0.5 * (x + 1), 0.5 * w
    rho = np.sqrt(1 - mu**2)  # rho d rho = mu d mu
    inten = np.polynomial.polynomial.polyval(mu, coeffs)
    phi = (np.arange(n_phi) + 0.5) * np.pi / n_phi  # upper half only
    y = rho[:, None] * np.sin(phi)[None, :]
    # direction elevation for a patch at angular offset (alpha rho) toward azimuth phi:
    # sin(elev) = sin(alpha rho) sin(phi)
    sin_el = np.sin(ALPHA * rho)[:, None] * np.sin(phi)[None, :]
    num = np.sum((wm * inten * mu)[:, None] * sin_el) * (np.pi / n_phi)
    den = np.sum(wm * inten * mu) * 2 * np.pi
    assert np.all(y >= 0)
    return num / den


@pytest.mark.parametrize("law", LAWS)
def test_weights_sum_to_one_and_flux_is_conserved(law):
    disk = il.sun_disk(law=law)
    assert disk.weights.sum() == pytest.approx(1.0, rel=1e-12, abs=0)
    assert np.all(disk.weights > 0)
    # a facet facing the Sun, nothing in the way: S0 (1 au/r)^2 * sum_j w_j cos(alpha rho_j).
    # The cosine factor is the only departure from S0/r^2 (second order, ~1e-5), so compare
    # against it at 1e-9 relative: the disk's weights carry exactly S0/r^2.
    r = np.array([0.983 * AU, 1.017 * AU])
    s = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    E = il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), s, r, 1361.0, disk)[:, 0]
    rho = np.hypot(*disk.offsets.T)
    alpha = np.arcsin(SUN_RADIUS / r)
    expect = 1361.0 * (AU / r) ** 2 * np.array([np.sum(disk.weights * np.cos(a * rho)) for a in alpha])
    np.testing.assert_allclose(E, expect, rtol=1e-9)
    assert np.all(np.abs(E / (1361.0 * (AU / r) ** 2) - 1) < 2e-5)


def test_law_shapes():
    mu = np.linspace(0, 1, 11)
    for law in LAWS:
        assert il.limb_darkening(1.0, law) == pytest.approx(1.0, abs=1e-12)
        assert np.all(il.limb_darkening(mu, law) > 0)
    assert il.limb_darkening(0.0, "linear") == pytest.approx(1 - il.LINEAR_U)
    assert il.limb_darkening(0.0, "quadratic") == pytest.approx(0.30)
    # Neckel & Labs band mean: limb at ~0.3 of the centre, between the 550 nm laws' 0.30-0.46
    assert 0.2 < il.limb_darkening(0.0, "neckel_labs") < 0.5
    # darkening is monotone: brighter toward the centre
    for law in ("linear", "quadratic", "neckel_labs"):
        assert np.all(np.diff(il.limb_darkening(mu, law)) > 0)


@pytest.mark.parametrize("law", LAWS)
def test_flat_facet_with_sun_centre_on_horizon(law):
    """Horizontal facet, Sun centre exactly on the horizon: only the upper half-disk lights it.

    For a point Sun the flux would be exactly 0; the extended disk gives S times the
    law-weighted mean of sin(elevation) over the upper half-disk, ~ S * alpha * 0.2.
    Sampling error bound: the convergence check (bench/sun_disk_convergence.py) finds the
    default 37-patch disk within 0.7% of S sin(alpha) over the whole grazing range, for every law.
    """
    exact = _exact_flat_horizon_flux(law)
    s = np.array([[0.0, -1.0, 0.0]])
    E = il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), s, [AU], 1.0, il.sun_disk(law=law))[0, 0]
    assert abs(E - exact) < 0.007 * np.sin(ALPHA)
    # and finer disks converge on it
    errs = [
        abs(il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), s, [AU], 1.0, il.sun_disk(n, law))[0, 0] - exact)
        for n in (2, 4, 8)
    ]
    assert errs[2] < errs[0]
    assert errs[2] < 0.002 * np.sin(ALPHA)


@pytest.mark.parametrize("law", LAWS)
def test_terrain_horizon_cuts_the_disk_in_half(law):
    """A facet facing the Sun, terrain horizon through the Sun's centre: half the flux.

    The sampled disk is symmetric about the horizon line, so the patches above it carry
    exactly half of the off-centre weight; the centre patch lies *on* the line (ray parallel
    to the terrain, counted as free), so the error is at most half its weight.
    """
    disk = il.sun_disk(law=law)
    s = np.array([[0.0, -1.0, 0.0]])
    E = il.direct_irradiance(_Facets([0, -1, 0]), _HorizonPlane(), s, [AU], 1.0, disk)[0, 0]
    half_cos = 0.5 * np.sum(disk.weights * np.cos(ALPHA * np.hypot(*disk.offsets.T)))
    assert abs(E - half_cos) <= 0.5 * disk.weights[0] + 1e-12
    # exact half-disk fraction by quadrature is 1/2 for every law
    assert il.disk_fraction_above(law, 0.0) == pytest.approx(0.5, abs=1e-12)


def test_partial_horizon_matches_exact_fraction_on_average():
    """Terrain horizon sweeping across the disk: mean error of the visible fraction.

    Measured (bench/sun_disk_convergence.py): 37 patches give a mean |error| of 1.7% of the
    full disk over a sunrise (max 9%, a single cell row crossing the horizon), 91 patches 0.9%.
    """
    h = np.linspace(-1.05, 1.05, 85)
    s = np.stack([np.zeros_like(h), -np.cos(h * ALPHA), np.sin(h * ALPHA)], 1)
    exact = np.array([il.disk_fraction_above("linear", -x) for x in h]) * np.cos(h * ALPHA)
    errs = []
    for n in (2, 4, 8):
        E = il.direct_irradiance(_Facets([0, -1, 0]), _HorizonPlane(), s, np.full(h.size, AU), 1.0, il.sun_disk(n))
        errs.append(np.abs(E[:, 0] - exact).mean())
    assert errs[0] > errs[1] > errs[2]
    assert errs[1] < 0.025


def test_point_sun_on_flat_facet_gives_S_cos_i():
    inc = np.deg2rad([0, 30, 60, 89, 90, 120])
    s = np.stack([np.zeros_like(inc), np.sin(inc), np.cos(inc)], 1)
    r = np.full(inc.size, 1.01 * AU)
    E = il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), s, r, 1361.0, None)[:, 0]
    expect = 1361.0 / 1.01**2 * np.maximum(0, np.cos(inc))
    np.testing.assert_allclose(E, expect, rtol=1e-12, atol=1e-9)


def test_disk_far_above_horizon_equals_point_sun_to_second_order():
    inc = np.deg2rad([10.0, 45.0, 80.0])
    s = np.stack([np.zeros_like(inc), np.sin(inc), np.cos(inc)], 1)
    r = np.full(inc.size, AU)
    point = il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), s, r, 1361.0, None)
    disk = il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), s, r, 1361.0, il.sun_disk())
    # second-order term: cos(i) * alpha^2 <rho^2>/2 ~ 1e-5 relative (alpha = 4.65e-3 rad)
    np.testing.assert_allclose(disk, point, rtol=2e-5)


def test_real_tracer_shadows_in_a_bowl():
    """With the geometry helper's mesh and tracer: shadows appear, lit facets get S cos i."""
    geometry = pytest.importorskip("crater_thermal.geometry")
    raytrace = pytest.importorskip("crater_thermal.raytrace")
    mesh = geometry.bowl_mesh(0.2, 400)
    tracer = raytrace.RayTracer(mesh)
    e = np.deg2rad(10.0)
    s = np.array([[0.0, np.cos(e), np.sin(e)]])
    E = il.direct_irradiance(mesh, tracer, s, [AU], 1365.0, None)[0]
    cosi = mesh.normals @ s[0]
    lit = E > 0
    assert 0.1 < lit.mean() < 0.9
    np.testing.assert_allclose(E[lit], 1365.0 * cosi[lit], rtol=1e-12)
    # the disk version agrees with the point Sun except on facets near the shadow edge
    Ed = il.direct_irradiance(mesh, tracer, s, [AU], 1365.0, il.sun_disk())[0]
    same = np.isclose(Ed, E, rtol=1e-4, atol=1e-6)
    assert same.mean() > 0.9
    # batching across time steps does not change results
    s2 = np.repeat(s, 7, axis=0)
    E2 = il.direct_irradiance(mesh, tracer, s2, np.full(7, AU), 1365.0, il.sun_disk(), chunk_rays=20_000)
    np.testing.assert_array_equal(E2, np.repeat(Ed[None], 7, axis=0))


def test_sun_direction_from_angles():
    np.testing.assert_allclose(il.sun_direction_from_angles(0, 0), [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(il.sun_direction_from_angles(0, 90), [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(il.sun_direction_from_angles(90, 123), [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(il.sun_direction_from_angles(30, 180), [0, -np.cos(np.pi / 6), 0.5], atol=1e-15)


@pytest.mark.parametrize(
    "call",
    [
        lambda: il.sun_disk(law="sepia"),
        lambda: il.sun_disk(0),
        lambda: il.sun_disk(2.5),
        lambda: il.sun_disk(law=(1.0, -2.0)),  # negative intensity at the limb
        lambda: il.sun_direction_from_angles(91.0),
        lambda: il.sun_direction_from_angles(10.0, float("nan")),
        lambda: il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), [[0, 0, 2.0]], [AU]),
        lambda: il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), [[0, 0, 1.0]], [0.0]),
        lambda: il.direct_irradiance(_Facets([0, 0, 1]), _NoOcclusion(), [[0, 0, 1.0]], [AU], -5.0),
    ],
)
def test_bad_input_raises_config_error(call):
    with pytest.raises(ConfigError):
        call()
