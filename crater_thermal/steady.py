"""``crater-thermal steady``: radiative equilibrium of a mesh under a fixed Sun (a command driver).

Loads and checks the mesh, builds the ray tracer and the view-factor operator, and solves
:func:`crater_thermal.radiosity.steady_state` (no conduction); the result is written through
:func:`crater_thermal.io.write_steady`. The physics lives in :mod:`crater_thermal.radiosity` and
:mod:`crater_thermal.illumination`; this module only wires them to files.

The operator and the solver are chosen as ``crater-thermal run`` chooses them (issue 20): ``"auto"``
view factors are the exact sparse matrix below ``vfoperator.AUTO_COMPRESSED_MIN_FACETS`` facets and the
compressed operator from there on (:func:`crater_thermal.vfoperator.resolve_method`, the function a run
uses), and the ``"auto"`` solver follows the operator (:func:`crater_thermal.radiosity.resolve_solver`:
LU with the exact matrix, the iterative scattering fixed point and GMRES with the compressed one). Both
can be forced; the written file says which were used (attributes ``view_factors``, ``solver``,
``scattering_solve``, ``ir_solve``, and what was requested).
"""

from __future__ import annotations

import numpy as np

from crater_thermal import illumination, io, radiosity, vfoperator
from crater_thermal.constants import ALBEDO, AU, EMISSIVITY, SOLAR_CONSTANT
from crater_thermal.errors import ConfigError
from crater_thermal.geometry import load_mesh
from crater_thermal.progress import bar
from crater_thermal.raytrace import RayTracer


def choose_methods(n_facets: int, view_factors: str = "auto", solver: str = "auto") -> tuple[str, str]:
    """The view-factor operator and the solver ``steady`` uses for a mesh of ``n_facets`` facets.

    Parameters
    ----------
    n_facets : int
    view_factors : {"auto", "exact", "compressed"}
        ``"auto"``: by facet count, as a run (:func:`crater_thermal.vfoperator.resolve_method`).
    solver : {"auto", "direct", "iterative"}
        ``"auto"``: by operator (:func:`crater_thermal.radiosity.resolve_solver`).

    Returns
    -------
    (view_factors, solver) : ``"exact"`` or ``"compressed"``, ``"direct"`` or ``"iterative"``.

    Raises
    ------
    ConfigError
        An unknown name, or the direct solver with the compressed operator.
    """
    kind = vfoperator.resolve_method(view_factors, int(n_facets))
    return kind, radiosity.resolve_solver(solver, kind)


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
    view_factors: str = "auto",
    tolerance: float | None = None,
    solver: str = "auto",
    cache_dir=None,
    overwrite: bool = False,
    flip: bool = False,
    progress: bool | None = None,
):
    """Load a mesh, solve the radiative equilibrium under a fixed Sun at 1 au, write it (``crater-thermal steady``).

    All inputs are checked before any work (ConfigError / MeshError / OutputExistsError).
    Angles in degrees (``sun_elevation_deg`` in [-90, 90], ``sun_azimuth_deg`` from north, clockwise),
    ``albedo`` and ``emissivity`` [-], ``solar_constant`` [W m-2] at 1 au.
    ``method``, ``n_bounces``: the scattering (:class:`crater_thermal.radiosity.ScatteringSolver`).
    ``view_factors`` ("auto" | "exact" | "compressed") and ``solver`` ("auto" | "direct" | "iterative"):
    see :func:`choose_methods`. ``tolerance`` [-]: the compressed operator's relative Frobenius error per
    far block, in (0, 0.1] (None: ``vfoperator.DEFAULT_TOLERANCE``, a case file's default).
    ``cache_dir``: folder caching the exact matrix by mesh hash.
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
    if tolerance is None:
        tolerance = vfoperator.DEFAULT_TOLERANCE
    tol = float(tolerance) if isinstance(tolerance, (int, float, np.number)) else float("nan")
    if not 0.0 < tol <= 0.1:  # the range vfoperator.compressed_view_factors accepts, checked before any work
        raise ConfigError(f"view-factor tolerance = {tolerance!r} is outside (0, 0.1]")
    choose_methods(0, view_factors, solver)  # unknown names, and direct + compressed, refused before any work
    disk = None if point_sun else illumination.sun_disk(n_rings or illumination.DEFAULT_N_RINGS, limb_darkening)
    out = io.check_output(output, overwrite, inputs=[mesh_path])
    with io.output_lock(out):
        mesh = load_mesh(mesh_path, flip=flip)
        kind, solver_kind = choose_methods(mesh.n_facets, view_factors, solver)
        tracer = RayTracer(mesh)
        with bar(f"view factors ({mesh.n_facets} facets, {kind})", progress) as report:
            F = vfoperator.view_factor_operator(
                mesh, tracer, method=kind, tolerance=tol, cache_dir=cache_dir, progress=report
            )
        res, how = radiosity.steady_solution(
            mesh, F, tracer, sun, AU, albedo, emissivity, solar_constant, disk, method, n_bounces, solver_kind
        )
        attrs = {
            "albedo": float(albedo),
            "emissivity": float(emissivity),
            "solar_constant": float(solar_constant),
            "sun_elevation_deg": float(sun_elevation_deg),
            "sun_azimuth_deg": float(sun_azimuth_deg),
            "sun_distance_au": 1.0,
            "sun_model": "point" if disk is None else f"disk, {disk.law} limb darkening, {disk.n_patches} patches",
            "scattering": method if method == "exact" else f"{n_bounces} bounces",
            "view_factors": kind,
            "view_factors_requested": view_factors,
            "view_factor_tolerance": tol if kind == "compressed" else None,
            "view_factor_bytes": int(F.nbytes),
            "solver": how["solver"],
            "solver_requested": solver,
            "scattering_solve": how["scattering_solve"],
            "ir_solve": how["ir_solve"],
            "ir_reflection": 0,
            "conduction": 0,
        }
        path = io.write_steady(out, mesh, res, attrs, overwrite=overwrite)
        return path, res
