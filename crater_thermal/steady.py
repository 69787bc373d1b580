"""``crater-thermal steady``: radiative equilibrium of a mesh under a fixed Sun (a command driver).

Loads and checks the mesh, builds the ray tracer and the view factors (cached by mesh hash), and
solves :func:`crater_thermal.radiosity.steady_state` (no conduction); the result is written through
:func:`crater_thermal.io.write_steady`. The physics lives in :mod:`crater_thermal.radiosity` and
:mod:`crater_thermal.illumination`; this module only wires them to files.
"""

from __future__ import annotations

import numpy as np

from crater_thermal import illumination, io, radiosity
from crater_thermal.constants import ALBEDO, AU, EMISSIVITY, SOLAR_CONSTANT
from crater_thermal.errors import ConfigError
from crater_thermal.geometry import load_mesh
from crater_thermal.progress import bar
from crater_thermal.raytrace import RayTracer
from crater_thermal.viewfactors import view_factor_matrix


def steady_file(
    mesh_path,
    output,
    sun_elevation_deg: float,
    sun_azimuth_deg: float = 180.0,
    albedo: float = ALBEDO,
    emissivity: float = EMISSIVITY,
    solar_constant: float = SOLAR_CONSTANT,
    point_sun: bool = False,
    limb_darkening: str = "linear",
    n_rings: int | None = None,
    method: str = "exact",
    n_bounces: int = radiosity.DEFAULT_BOUNCES,
    cache_dir=None,
    overwrite: bool = False,
    flip: bool = False,
    progress: bool | None = None,
):
    """Load a mesh, solve the radiative equilibrium under a fixed Sun at 1 au, write it (``crater-thermal steady``).

    All inputs are checked before any work (ConfigError / MeshError / OutputExistsError).
    ``flip`` reverses the mesh's winding (see :func:`crater_thermal.geometry.load_mesh`);
    ``progress``: a bar for the view factors (default: only on a terminal).

    Returns
    -------
    (path, results) : the written path and the :func:`crater_thermal.radiosity.steady_state` dict.
    """
    sun = illumination.sun_direction_from_angles(sun_elevation_deg, sun_azimuth_deg)
    radiosity.check_per_facet("albedo", albedo, 1, 0.0, 1.0, hi_open=True)
    radiosity.check_per_facet("emissivity", emissivity, 1, 0.0, 1.0, hi_open=False)
    if not emissivity > 0:
        raise ConfigError(f"emissivity = {emissivity!r} is outside (0, 1]")
    if not np.isfinite(solar_constant) or solar_constant < 0:
        raise ConfigError(f"solar_constant = {solar_constant!r} W m-2 must be finite and >= 0")
    if method not in radiosity.SCATTERING_METHODS:
        raise ConfigError(f"scattering method = {method!r}; allowed: {', '.join(radiosity.SCATTERING_METHODS)}")
    disk = None if point_sun else illumination.sun_disk(n_rings or illumination.DEFAULT_N_RINGS, limb_darkening)
    out = io.check_output(output, overwrite)
    mesh = load_mesh(mesh_path, flip=flip)
    tracer = RayTracer(mesh)
    with bar(f"view factors ({mesh.n_facets} facets)", progress) as report:
        F = view_factor_matrix(mesh, tracer, cache_dir=cache_dir, progress=report)
    res = radiosity.steady_state(mesh, F, tracer, sun, AU, albedo, emissivity, solar_constant, disk, method, n_bounces)
    attrs = {
        "albedo": float(albedo),
        "emissivity": float(emissivity),
        "solar_constant": float(solar_constant),
        "sun_elevation_deg": float(sun_elevation_deg),
        "sun_azimuth_deg": float(sun_azimuth_deg),
        "sun_distance_au": 1.0,
        "sun_model": "point" if disk is None else f"disk, {disk.law} limb darkening, {disk.n_patches} patches",
        "scattering": method if method == "exact" else f"{n_bounces} bounces",
        "ir_reflection": 0,
        "conduction": 0,
    }
    path = io.write_steady(out, mesh, res, attrs, overwrite=overwrite)
    return path, res
