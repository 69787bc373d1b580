"""Small synthetic run and replay datasets in the schemas of crater_thermal.io (``run_dataset``,
``replay_dataset``), for tests.

Nothing here is a physics reference: the numbers are only meant to *look* like a polar crater run
so that analysis, report and viz can be exercised quickly.

* Mesh: a crater-like triangulated disk. Cross-section: flat floor (r <= floor_radius), a circular
  arc wall tangent to the floor rising to the rim crest at rim_radius, a straight outer flank down
  to the plain at rim_radius + rim_width, and a flat surround. Revolved, Delaunay-triangulated in
  plan view, faces oriented counter-clockwise seen from above (normals up).
* Sun: at latitude ``lat_deg`` the Sun's elevation is approximately
  ``(90 deg - |lat|) cos(H) + declination(t)`` with hour angle H advancing once per synodic
  month; its azimuth follows H (equatorward at local noon: +y for a southern crater).
* Shadows: marching along the Sun direction over the analytic height profile.
* Fluxes/temperatures: direct + a crude scattered term; IR from a mean-crater view factor; the
  temperature relaxes (in T^4) towards radiative equilibrium with a 1.5-day time constant plus a
  floor heat flux that keeps the night near ~50 K, like thesis Fig. 7.5.
* Replay: the nominal profile equals the run; other two-layer profiles are colder at night and
  very slightly warmer by day, dominated by the bottom density (thesis 7.2); rock is warmer at
  night by ~25 K.
"""

from __future__ import annotations

import json

import numpy as np
import xarray as xr
from scipy.spatial import Delaunay

from crater_thermal.constants import ALBEDO, EMISSIVITY, LUNAR_DAY, SIGMA, SOLAR_CONSTANT

GEOM = dict(
    floor_radius_m=300.0, rim_radius_m=1000.0, depth_m=400.0, rim_height_m=70.0, rim_width_m=500.0, surround_m=300.0
)


def height(r, g=GEOM):
    """Analytic height z(r) [m] of the synthetic crater (plain at z = 0)."""
    r = np.asarray(r, dtype=float)
    rf, rr, d, h, w = g["floor_radius_m"], g["rim_radius_m"], g["depth_m"], g["rim_height_m"], g["rim_width_m"]
    zf = h - d
    # circle tangent to the floor at r = rf: centre (rf, zf + R), through (rr, h)
    dx, dz = rr - rf, h - zf
    R = (dx**2 + dz**2) / (2 * dz)
    z = np.where(r <= rf, zf, 0.0)
    wall = (r > rf) & (r <= rr)
    z = np.where(wall, zf + R - np.sqrt(np.clip(R**2 - (r - rf) ** 2, 0, None)), z)
    flank = (r > rr) & (r <= rr + w)
    z = np.where(flank, h * (1 - (r - rr) / w), z)
    return z


def crater_mesh(n_rings=14, g=GEOM):
    """Vertices (nv, 3) [m] and faces (nf, 3) of the synthetic crater."""
    r_out = g["rim_radius_m"] + g["rim_width_m"] + g["surround_m"]
    radii = np.unique(
        np.concatenate(
            [
                np.linspace(0, g["floor_radius_m"], 4),
                np.linspace(g["floor_radius_m"], g["rim_radius_m"], 6),
                np.linspace(g["rim_radius_m"], g["rim_radius_m"] + g["rim_width_m"], 3),
                [r_out],
            ]
        )
    )
    pts = [[0.0, 0.0]]
    for i, r in enumerate(radii[1:]):
        n = max(6, int(round(2 * np.pi * r / (r_out / n_rings))))
        a = np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.5 * i
        pts.extend(np.column_stack([r * np.cos(a), r * np.sin(a)]).tolist())
    xy = np.asarray(pts)
    faces = Delaunay(xy).simplices.astype(np.int64)
    a, b, c = xy[faces[:, 0]], xy[faces[:, 1]], xy[faces[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    faces[cross < 0] = faces[cross < 0][:, [0, 2, 1]]
    z = height(np.hypot(xy[:, 0], xy[:, 1]), g)
    return np.column_stack([xy, z]), faces


def _facet_geometry(v, f):
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cr = np.cross(p1 - p0, p2 - p0)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    normal = cr / (2 * area[:, None])
    centroid = (p0 + p1 + p2) / 3
    return area, normal, centroid


def sun_series(lat_deg=-86.0, n_lunar_days=2.0, step_h=4.0, start="2019-01-01T00:00"):
    """Times (nt,) datetime64[ns], unit Sun directions (nt, 3) and distances (nt,) [au]."""
    nt = int(n_lunar_days * LUNAR_DAY / (step_h * 3600)) + 1
    t = np.arange(nt) * step_h * 3600.0
    times = np.datetime64(start, "ns") + (t * 1e9).astype("timedelta64[ns]")
    H = 2 * np.pi * t / LUNAR_DAY
    dec = np.deg2rad(1.54) * np.sin(2 * np.pi * t / (365.25 * 86400) + 0.3)
    colat = np.deg2rad(90.0 - abs(lat_deg))
    # a southern site sees the Sun higher when the declination is negative (and vice versa)
    el = np.arcsin(np.sin(colat) * np.cos(H)) - np.sign(lat_deg) * dec
    south = lat_deg < 0
    az = H  # from north, clockwise; at noon the Sun is equatorward
    north_comp = np.cos(az) * np.cos(el) * (1 if south else -1)
    east_comp = np.sin(az) * np.cos(el) * (1 if south else -1)
    dirs = np.column_stack([east_comp, north_comp, np.sin(el)])
    dist = 1.0 + 0.016 * np.cos(2 * np.pi * t / (365.25 * 86400))
    return times, dirs / np.linalg.norm(dirs, axis=1, keepdims=True), dist


def _shadowed(centroid, sdir, g=GEOM, n_steps=60):
    """(nf,) True where terrain blocks the Sun (ray-march over the analytic height profile)."""
    if sdir[2] <= 0:
        return np.ones(len(centroid), bool)
    r_out = g["rim_radius_m"] + g["rim_width_m"]
    horiz = np.hypot(sdir[0], sdir[1])
    s_max = 2 * r_out / max(horiz, 1e-9)
    s = np.linspace(1.0, s_max, n_steps)
    p = centroid[:, None, :] + s[None, :, None] * sdir[None, None, :]
    zt = height(np.hypot(p[..., 0], p[..., 1]), g)
    return np.any(zt > p[..., 2] + 1.0, axis=1)


def make_run(lat_deg=-86.0, n_lunar_days=2.0, step_h=4.0, n_rings=14, nominal="1300/1800"):
    """A synthetic *run* dataset (contract schema)."""
    v, f = crater_mesh(n_rings)
    area, normal, centroid = _facet_geometry(v, f)
    times, sdir, dist = sun_series(lat_deg, n_lunar_days, step_h)
    nt, nf = len(times), len(f)
    direct = np.zeros((nt, nf))
    for i in range(nt):
        cosi = normal @ sdir[i]
        lit = (cosi > 0) & ~_shadowed(centroid, sdir[i])
        direct[i] = np.where(lit, SOLAR_CONSTANT / dist[i] ** 2 * cosi, 0.0)
    # crude bowl view factor: facets inside the rim see ~20% crater
    r = np.hypot(centroid[:, 0], centroid[:, 1])
    fview = np.where(r < GEOM["rim_radius_m"], 0.1, 0.02)
    lit_mean = (direct * area).sum(1) / area.sum()
    solar = direct + ALBEDO * fview[None, :] * lit_mean[:, None]
    # temperatures: relax T^4 towards equilibrium (tau = 1.5 d), floor flux keeps nights ~50 K
    q_floor = EMISSIVITY * SIGMA * 48.0**4
    dt = step_h * 3600.0
    decay = np.exp(-dt / (1.5 * 86400.0))
    u = np.full(nf, 60.0**4)
    T = np.zeros((nt, nf))
    ir = np.zeros((nt, nf))
    for i in range(nt):
        ir[i] = fview * EMISSIVITY * SIGMA * np.mean(u)
        absorbed = (1 - ALBEDO) * solar[i] + EMISSIVITY * ir[i] + q_floor
        u_eq = absorbed / (EMISSIVITY * SIGMA)
        u = u_eq + (u - u_eq) * decay if i else u_eq
        T[i] = u**0.25
    meta = dict(kind="crater", diameter_m=2 * GEOM["rim_radius_m"], **GEOM)
    ds = xr.Dataset(
        {
            "surface_temperature": (("time", "facet"), T, {"units": "K"}),
            "solar_incident": (("time", "facet"), solar, {"units": "W m-2"}),
            "ir_incident": (("time", "facet"), ir, {"units": "W m-2"}),
            "solar_direct": (("time", "facet"), direct, {"units": "W m-2"}),
            "sun_direction": (("time", "xyz"), sdir, {"units": "1"}),
            "sun_distance": (("time",), dist, {"units": "au"}),
            "mesh_vertices": (("vertex", "xyz"), v, {"units": "m"}),
            "mesh_faces": (("facet", "corner"), f),
            "area": (("facet",), area, {"units": "m2"}),
            "normal": (("facet", "xyz"), normal, {"units": "1"}),
            "centroid": (("facet", "xyz"), centroid, {"units": "m"}),
        },
        coords={"time": times},
        attrs=dict(
            lat_deg=float(lat_deg),
            lon_deg=0.0,
            albedo=ALBEDO,
            emissivity=EMISSIVITY,
            mesh_hash=f"synthetic{n_rings:04d}abcd"[:16],
            nominal_profile=nominal,
            mesh_meta=json.dumps(meta),
            case_toml="# synthetic",
            software_version="test",
            property_set="apollo",
        ),
    )
    return ds


def _profile_T(run, top, bottom, rock=False):
    T = run["surface_temperature"].values
    lit = run["solar_direct"].values > 0
    # day weight: recently lit facets (smoothed over ~1 day)
    k = np.ones(6) / 6
    w = np.apply_along_axis(lambda c: np.convolve(c, k, mode="same"), 0, lit.astype(float))
    if rock:
        return T + 25.0 * (1 - w) - 8.0 * w
    # facets with larger swings (Sun-facing walls) differ more (thesis 7.2, Fig. 7.7b)
    swing = 1.0 + 0.5 * run["solar_direct"].values.mean(0) / max(run["solar_direct"].values.mean(0).max(), 1e-9)
    night = (-2.5 * (1800.0 - bottom) / 700.0 - 0.5 * (1300.0 - top) / 500.0) * swing
    day = -0.1 * night
    return T + night * (1 - w) + day * w


def make_replay(run, grid=True):
    """A synthetic *replay* dataset for ``run``: nominal, loose, rock, and a small density grid."""
    profs = [(1300.0, 1800.0), (800.0, 1100.0)]
    if grid:
        for top in (800.0, 1300.0, 1800.0):
            for bottom in (1100.0, 1800.0, 2000.0):
                if top <= bottom and (top, bottom) not in profs:
                    profs.append((top, bottom))
    labels = [f"{int(a)}/{int(b)}" for a, b in profs] + ["rock"]
    temps = [_profile_T(run, a, b) for a, b in profs] + [_profile_T(run, 0, 0, rock=True)]
    temps[0] = run["surface_temperature"].values.copy()
    rt = [a for a, _ in profs] + [3070.0]
    rb = [b for _, b in profs] + [3070.0]
    keep = [
        k for k in run.data_vars if k not in ("surface_temperature", "solar_incident", "ir_incident", "solar_direct")
    ]
    ds = run[keep].copy()
    ds["surface_temperature"] = (("profile", "time", "facet"), np.stack(temps), {"units": "K"})
    ds = ds.assign_coords(
        profile=np.array(labels, dtype=object),
        rho_top=("profile", np.array(rt), {"units": "kg m-3"}),
        rho_bottom=("profile", np.array(rb), {"units": "kg m-3"}),
    )
    ds.attrs = dict(run.attrs)
    return ds


def write_pair(tmp_path, **kw):
    """Write a run and replay to ``tmp_path``; return their paths."""
    run = make_run(**kw)
    rep = make_replay(run)
    rp, pp = tmp_path / "run.nc", tmp_path / "replay.nc"
    run.to_netcdf(rp)
    rep.to_netcdf(pp)
    return rp, pp
