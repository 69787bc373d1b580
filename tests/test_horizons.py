"""Horizon-map sunlight (crater_thermal.horizons) against the ray-traced disk, and its disk-segment tables."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest

from crater_thermal import choices, config, ephemeris, horizons, illumination, io, runner
from crater_thermal.errors import ConfigError, MeshError
from crater_thermal.geometry import bowl_mesh, crater_mesh, load_mesh
from crater_thermal.raytrace import RayTracer
from crater_thermal.reference import rough_site

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------ segment tables


def _segment_by_quadrature(coeffs, h, n=48):
    """Fraction and first moment above ``y = h`` by 2-D Gauss-Legendre quadrature, chord by chord.

    ``y = cos t`` (t in [0, arccos h]) and ``x = sin t sin u`` (u in [-pi/2, pi/2]) make the integrand a
    polynomial in sines and cosines (``mu = sin t cos u``), so the rule converges spectrally.
    """
    theta = math.acos(h)
    xt, wt = np.polynomial.legendre.leggauss(n)
    t = 0.5 * theta * (xt + 1.0)
    u = 0.5 * math.pi * xt
    T, U = np.meshgrid(t, u, indexing="ij")
    W = np.outer(0.5 * theta * wt, 0.5 * math.pi * wt)
    mu = np.sin(T) * np.cos(U)
    jac = np.sin(T) * np.sin(T) * np.cos(U)  # dy dx = sin t dt * sin t cos u du
    inten = np.polynomial.polynomial.polyval(mu, coeffs)
    total = 2.0 * math.pi * sum(c / (k + 2) for k, c in enumerate(coeffs))  # int I dA over the disk
    frac = float(np.sum(W * inten * jac)) / total
    mom = float(np.sum(W * inten * jac * np.cos(T))) / total
    return frac, mom


@pytest.mark.parametrize("law", sorted(choices.LIMB_DARKENING_LAWS) + [(0.2, 0.5, 0.3)])
def test_segment_table_matches_direct_integration(law):
    coeffs = illumination.law_coefficients(law)
    hs = np.concatenate([np.linspace(-1.0, 1.0, 21), [-0.9999, -0.3333, 0.123, 0.9999]])
    frac, mom = horizons.disk_segment(hs, law)
    for h, f, g in zip(hs, frac, mom):
        f_ref, g_ref = _segment_by_quadrature(coeffs, float(h))
        # the brief's 1e-6: the table is the closed form sampled at 4097 values of arccos(h), interpolated
        assert f == pytest.approx(f_ref, abs=1e-6)
        assert g == pytest.approx(g_ref, abs=1e-6)
    # and adaptive 2-D quadrature in plain Cartesian coordinates (scipy) agrees
    from scipy import integrate

    def inten(x, y):
        return np.polynomial.polynomial.polyval(math.sqrt(max(0.0, 1.0 - x * x - y * y)), coeffs)

    total = 2.0 * math.pi * sum(c / (k + 2) for k, c in enumerate(coeffs))
    for h in (0.45,):
        ref = (
            integrate.dblquad(
                inten,
                h,
                1.0,
                lambda y: -math.sqrt(1.0 - y * y),
                lambda y: math.sqrt(1.0 - y * y),
                epsabs=1e-11,
                epsrel=1e-11,
            )[0]
            / total
        )
        assert horizons.disk_segment(h, law)[0] == pytest.approx(ref, abs=1e-6)


def test_segment_table_limits():
    frac, mom = horizons.segment_tables("linear")
    assert frac[0] == 0.0 and frac[-1] == pytest.approx(1.0, abs=1e-15)
    assert mom[0] == pytest.approx(0.0, abs=1e-15) and mom[-1] == pytest.approx(0.0, abs=1e-15)
    assert np.all(np.diff(frac) >= 0)
    f0, _ = horizons.disk_segment(0.0, "uniform")
    assert f0 == pytest.approx(0.5, abs=1e-12)
    # uniform disk: segment area (t - sin t cos t) / pi above y = cos t
    t = 1.1
    assert horizons.disk_segment(math.cos(t), "uniform")[0] == pytest.approx(
        (t - math.sin(t) * math.cos(t)) / math.pi, abs=1e-7
    )
    with pytest.raises(ConfigError):
        horizons.segment_tables("purple")


# ---------------------------------------------------------------------------------------- horizons


def test_bowl_centre_horizon_is_the_rim():
    # a facet next to the lowest point of a spherical bowl sees the rim at atan(depth / distance)
    m = bowl_mesh(0.2, 4000, diameter_m=1000.0)
    tr = RayTracer(m)
    f = int(np.argmin(np.hypot(m.centroids[:, 0], m.centroids[:, 1])))
    az = np.linspace(0.0, 2 * math.pi, 24, endpoint=False)
    H = horizons.trace_horizons(tr, [f], az, tolerance_deg=0.001)[0]
    o = tr.origins[f]
    d = np.stack([np.sin(az), np.cos(az)], axis=1)
    # distance along each azimuth from the origin to the rim circle r = 500 m
    b = d @ o[:2]
    dist = -b + np.sqrt(b * b - (o[:2] @ o[:2] - 500.0**2))
    expected = np.degrees(np.arctan2(0.0 - o[2], dist))
    # the rim is a polygon of ~150 vertices, so it sags by up to 500 m * (1 - cos(pi / 150)) = 0.11 m
    # below the circle: 0.02 deg from ~700 m
    assert np.degrees(H) == pytest.approx(expected, abs=0.03)


def test_horizon_map_cache_and_checks(tmp_path):
    m = crater_mesh(10.0, 200)
    tr = RayTracer(m)
    a = horizons.horizon_map(m, tr, n_azimuths=16, cache_dir=tmp_path)
    files = list(tmp_path.glob("horizons_*.npz"))
    assert len(files) == 1 and m.hash in files[0].name
    b = horizons.horizon_map(m, tr, n_azimuths=16, cache_dir=tmp_path)
    assert b.build_s == 0.0 and np.array_equal(a.elevation, b.elevation)
    assert a.elevation.shape == (16, 200) and a.elevation.dtype == np.float32
    # the map at a sampled azimuth is the sampled column
    assert np.allclose(a.at(a.azimuths[3]), a.elevation[3])
    with pytest.raises(ConfigError, match="n_azimuths"):
        horizons.horizon_map(m, tr, n_azimuths=4)
    with pytest.raises(MeshError):
        horizons.direct_irradiance_horizon(crater_mesh(10.0, 202), a, np.array([[0.0, 0.6, 0.8]]), 1.5e11)


# -------------------------------------------------------------------------- flux vs the ray-traced disk


def _lunation(lat_deg=-85.0, step_h=4.0):
    times = ephemeris.time_grid("2024-01-11", "2024-02-09T12:00", step_h * 3600.0)
    return ephemeris.sun_in_crater_frame(times, lat_deg, 0.0)


@functools.lru_cache(maxsize=4)
def _reference(which, n_rings=8):
    """Mesh, tracer, Sun series and ray-traced direct flux (``n_rings`` disk), shared by tests."""
    if which == "crater502":
        mesh = load_mesh(REPO / "meshes" / "crater_10km_502.ply")
    elif which == "crater1200":
        mesh = crater_mesh(10.0, 1200)
    else:
        mesh = rough_site(1500)
    s, r = _lunation()
    tr = RayTracer(mesh)
    return mesh, tr, s, r, illumination.direct_irradiance(mesh, tr, s, r, disk=illumination.sun_disk(n_rings))


def _compare_lunation(which, n_az=horizons.DEFAULT_N_AZIMUTHS):
    mesh, tr, s, r, E_rays = _reference(which)
    hmap = horizons.horizon_map(mesh, tr, n_azimuths=n_az)
    E_hor = horizons.direct_irradiance_horizon(mesh, hmap, s, r)
    return mesh, E_rays.mean(axis=0), E_hor.mean(axis=0)


@pytest.mark.parametrize("which, n_az", [("crater502", None), ("crater1200", None), ("rough1500", 1440)])
def test_lunation_flux_matches_ray_traced_disk(which, n_az):
    # reference: the ray-traced disk with 8 rings (169 patches); its own default of 4 rings (37 patches)
    # quantises a half-hidden disk into 1/37ths of the flux, up to ~4 % of the lunation mean on facets
    # lit only at grazing Sun (measured on the 502-facet crater against 16 rings)
    mesh, I_rays, I_hor = _compare_lunation(which, n_az=n_az or horizons.DEFAULT_N_AZIMUTHS)
    diff = np.abs(I_hor - I_rays)
    # the criterion: lunation mean within 1 % where it is substantial, 1 W m-2 where tiny
    assert np.all(diff <= np.maximum(0.01 * I_rays, 1.0)), (diff.max(), np.argmax(diff))
    # overall energy: the area-weighted mean flux agrees to 0.1 % (measured <= 1e-4)
    w = mesh.areas
    assert np.sum(w * I_hor) == pytest.approx(np.sum(w * I_rays), rel=1e-3)
    # facets never lit by the rays stay (nearly) dark
    dark = I_rays == 0
    assert np.all(I_hor[dark] < 0.05)


def test_rough_site_default_azimuths():
    # At the default 720 azimuths (0.5 deg) a rough site's near-field horizon jumps (a hill's edge a
    # facet or two away: the horizon changes by degrees within 0.1 deg of azimuth) are interpolated
    # across a whole sample interval; when the Sun sits on such a jump at one of the lunation's 178
    # samples the step's flux is off by up to ~400 W m-2 (as is a 169-patch disk's, to a lesser
    # degree), i.e. ~2 W m-2 of the lunation mean on a handful of facets.  1440 azimuths meet the
    # criterion everywhere (test above); at 720, 99 % of the facets do and none is off by > 3 W m-2.
    _, I_rays, I_hor = _compare_lunation("rough1500")
    diff = np.abs(I_hor - I_rays)
    assert np.mean(diff <= np.maximum(0.01 * I_rays, 1.0)) >= 0.99
    assert diff.max() < 3.0


@pytest.mark.parametrize("which", ["crater", "rough", "dem"])
def test_hierarchical_map_matches_full_bisection(which, tmp_path):
    # horizon_map predicts most azimuths from their neighbours and re-brackets outward where the
    # prediction misses; on a height field the blocked/free boundary is unique, so every facet and
    # azimuth must land within the final bracket (180 / 2^15 deg) of a full bisection of [-90, 90] deg
    if which == "crater":
        mesh = crater_mesh(10.0, 3000)
    elif which == "rough":
        mesh = rough_site(3000)
    else:  # a DEM lattice: the 10 km crater rasterized and meshed by mesh dem (curvature included)
        from crater_thermal import terrain

        z, tr, wkt = terrain.synthetic_heights(-87.0, 45.0, 18.0, 50.0, craters=[(10.0, 0.0, 0.0)])
        dem = terrain.write_geotiff(tmp_path / "c.tif", z, tr, wkt)
        mesh = terrain.site_mesh(dem, -87.0, 45.0, 7.6, 250.0)
    tr = RayTracer(mesh)
    idx = np.sort(np.random.default_rng(3).choice(mesh.n_facets, 250, replace=False))
    az = np.arange(720) * (2.0 * math.pi / 720)
    fast = horizons._trace_hierarchical(tr, idx, 720, horizons.DEFAULT_TOLERANCE_DEG, horizons.CHUNK_RAYS)
    full = horizons.trace_horizons(tr, idx, az, horizons.DEFAULT_TOLERANCE_DEG)
    final_deg = 180.0 / 2**15
    assert np.degrees(np.abs(fast - full)).max() <= final_deg * (1.0 + 1e-6)


def test_point_sun_horizon_equals_point_sun_rays():
    # a point Sun is lit exactly when it is above the traced horizon: the two methods differ only on
    # steps where the Sun is within the horizon tolerance (0.005 deg) or interpolation error of it
    mesh = load_mesh(REPO / "meshes" / "crater_10km_502.ply")
    s, r = _lunation(step_h=6.0)
    tr = RayTracer(mesh)
    E_rays = illumination.direct_irradiance(mesh, tr, s, r, disk=None)
    hmap = horizons.horizon_map(mesh, tr, n_azimuths=720)
    E_hor = horizons.direct_irradiance_horizon(mesh, hmap, s, r, law=None)
    differ = np.abs(E_rays - E_hor) > 1e-6
    assert differ.mean() < 2e-3
    assert np.allclose(E_rays[~differ], E_hor[~differ], rtol=1e-9, atol=1e-9)


# ---------------------------------------------------------------------------------- coupled runs


CASE = """
name = "{name}"
[crater]
kind = "crater"
diameter_km = 10.0
facets = 502
[location]
lat_deg = -85.0
[period]
start = "2024-01-11"
end = "2024-02-09T12:00"
spinup = "periodic"
spinup_days = 29.53
periodic_tol_K = 0.001
[sun]
method = "{method}"
"""


def test_case_key_and_choices():
    assert horizons.SUN_METHODS is choices.SUN_METHODS == ("rays", "horizon")
    case = config.loads_case(CASE.format(name="x", method="horizon"))
    assert case.sun.method == "horizon" and case.sun.horizon_azimuths == horizons.DEFAULT_N_AZIMUTHS
    with pytest.raises(ConfigError, match="method"):
        config.loads_case(CASE.format(name="x", method="sunbeams"))
    with pytest.raises(ConfigError, match="horizon_azimuths"):
        config.loads_case(CASE.format(name="x", method="rays") + "horizon_azimuths = 90\n")


@pytest.mark.slow
def test_coupled_run_temperatures_match(tmp_path, monkeypatch):
    # One lunation recorded from its converged periodic state (the periodic spin-up iterates the same
    # forcing to 0.001 K): a year's later lunations differ only by the slow drift of the Sun's
    # declination, which both methods follow alike, so a lunation shows the methods' difference at a
    # fraction of a year's cost (~2 x 15 s).  Reference: the ray-traced disk with 8 rings (169 patches).
    monkeypatch.setenv("CRATER_THERMAL_CACHE", str(tmp_path / "cache"))
    runs = {}
    for method, extra in (("rays", "n_rings = 8\n"), ("horizon", "")):
        case = config.loads_case(CASE.format(name=method, method=method) + extra)
        runs[method] = io.open_run(runner.run_case(case, tmp_path / f"{method}.nc", progress=False))
    a, b = runs["rays"], runs["horizon"]
    dT = b["surface_temperature"].values - a["surface_temperature"].values
    lit = (a["solar_direct"].values > 0) | (b["solar_direct"].values > 0)
    both = (a["solar_direct"].values > 0) & (b["solar_direct"].values > 0)

    def facet_mean(x, mask):
        return np.where(mask, x, 0.0).sum(axis=0) / np.maximum(mask.sum(axis=0), 1)

    # night-time (no direct Sun in either run), per facet: within 0.05 K (measured 0.047 K)
    assert np.abs(facet_mean(dT, ~lit)).max() < 0.05
    # daytime (Sun on the facet in both), per facet: 99 % within 0.5 K (measured p99 0.40 K, worst
    # 0.57 K on a facet lit by a grazing, half-hidden Sun); the reference's own disk discretisation
    # moves the same statistic by up to 3.7 K (37 against 169 patches)
    day = np.abs(facet_mean(dT, both))[both.any(axis=0)]
    assert np.percentile(day, 99) < 0.5 and day.max() < 1.0
    assert (tmp_path / "cache" / "horizons").is_dir()
