"""Sunlight on a mesh for any block of samples: direct (horizon map or ray-traced solar disk) and scattered.

One object per run (:class:`Sunlight`) holds what is made once per mesh (the horizon map, the
scattering solver) and computes blocks of samples on demand, so that a run streams its sunlight
through memory. It composes the physics modules that own each part:

* direct irradiance: :func:`crater_thermal.horizons.direct_irradiance_horizon` (``[sun] method =
  "horizon"``, the default: each facet's horizon elevation at 720 azimuths against the limb-darkened
  disk) or :func:`crater_thermal.illumination.direct_irradiance` (``"rays"``: Embree rays to the
  sampled disk);
* scattered sunlight: :class:`crater_thermal.radiosity.ScatteringSolver` (Lambertian, exact or a
  number of bounces);
* an incidence-dependent albedo A(i) of direct light: :func:`absorbed_sunlight`.

All irradiances are in W m-2; Sun directions are unit vectors in the mesh frame, distances in m.
"""

from __future__ import annotations

import contextlib
from typing import Callable, Optional

import numpy as np

from crater_thermal import cache, horizons, illumination, radiosity
from crater_thermal.errors import MeshError


def _stage(progress, description: str):
    return progress(description) if progress else contextlib.nullcontext(None)


class Sunlight:
    """Direct and scattered sunlight with a case's ``[sun]``, ``[surface]`` and ``[scattering]`` settings.

    Parameters
    ----------
    sun : config.Sun
        ``method`` ("horizon" | "rays"), the disk (``point_sun``, ``limb_darkening``, ``n_rings``),
        ``horizon_azimuths``, ``solar_constant_W_m2``.
    surface : config.Surface or None
        ``albedo`` [-] and ``albedo_model`` (incidence dependence of direct light); None with ``F``
        None (direct light only).
    scattering : config.Scattering or None
        ``method`` and ``n_bounces``; None with ``F`` None.
    mesh, tracer : the mesh and its ray tracer.
    F : view-factor operator, or None (no scattering: flat ground, or direct light only).
    timer : optional ``timer(name)`` context factory; the horizon map's build (or cache read) is timed
        as "horizons", each block's direct light as "direct" and scattering as "radiosity".
    progress : optional reporter (:mod:`crater_thermal.progress`) for the horizon map.
    hmap : horizons.HorizonMap, optional
        The horizon map of ``mesh`` already traced (:func:`horizon_map`, e.g. on another thread while
        the view factors were built); traced here when None (method "horizon" only).
    """

    def __init__(
        self, sun, surface, scattering, mesh, tracer, F, timer: Optional[Callable] = None, progress=None, hmap=None
    ):
        timer = timer or _no_timer
        self.sun, self.surface, self.mesh, self.tracer, self.F = sun, surface, mesh, tracer, F
        self.method = sun.method
        self.hmap = self.disk = None
        if self.method == "horizon" and hmap is not None:
            if hmap.mesh_hash != mesh.hash:
                raise MeshError("Sunlight: the horizon map given was traced on a different mesh")
            self.hmap = hmap
        elif self.method == "horizon":
            with timer("horizons"), _stage(progress, f"horizon map ({mesh.n_facets} facets)") as report:
                self.hmap = horizon_map(sun, mesh, tracer, report)
        elif not sun.point_sun:
            self.disk = illumination.sun_disk(
                **({"n_rings": sun.n_rings} if sun.n_rings else {}), law=sun.limb_darkening
            )
        self.scat = (
            None
            if F is None
            else radiosity.ScatteringSolver(F, surface.albedo, method=scattering.method, n_bounces=scattering.n_bounces)
        )

    def __call__(self, sun_dirs, sun_dist_m, timer: Optional[Callable] = None, progress=None):
        """``(direct, solar)`` (n, nf) [W m-2] for Sun directions (n, 3) and distances (n,) [m].

        ``progress``: optional ``(done, total)`` callback of the ray-traced disk (method "rays")."""
        timer = timer or _no_timer
        sun = self.sun
        with timer("direct"):
            if self.method == "horizon":
                direct = horizons.direct_irradiance_horizon(
                    self.mesh,
                    self.hmap,
                    sun_dirs,
                    sun_dist_m,
                    solar_constant=sun.solar_constant_W_m2,
                    law=None if sun.point_sun else sun.limb_darkening,
                )
            else:
                direct = illumination.direct_irradiance(
                    self.mesh,
                    self.tracer,
                    sun_dirs,
                    sun_dist_m,
                    solar_constant=sun.solar_constant_W_m2,
                    disk=self.disk,
                    progress=progress,
                )
        with timer("radiosity"):
            solar = direct if self.scat is None else self.scat.solar_incident(direct)
        return direct, solar

    @property
    def incidence_dependent(self) -> bool:
        """Whether direct sunlight is reflected with an incidence-dependent albedo A(i)."""
        return self.surface is not None and self.surface.albedo_model != "constant"

    def with_absorbed(self, sun_dirs, sun_dist_m, timer: Optional[Callable] = None):
        """``(direct, solar, absorbed)`` (n, nf) [W m-2]; ``absorbed`` is None for a constant albedo
        (then it is ``(1 - A) solar``), else :func:`absorbed_sunlight` with the ``albedo_model``
        (and ``solar`` its scattered light of A(i)-reflected direct light)."""
        timer = timer or _no_timer
        if not self.incidence_dependent:
            return (*self(sun_dirs, sun_dist_m, timer), None)
        scat, self.scat = self.scat, None  # direct light only: the scattering is done with A(i) below
        try:
            direct, _ = self(sun_dirs, sun_dist_m, timer)
        finally:
            self.scat = scat
        with timer("radiosity"):
            solar, absorbed = absorbed_sunlight(self.surface, self.mesh, sun_dirs, direct, scat, self.F)
        return direct, solar, absorbed


def horizon_map(sun, mesh, tracer, progress=None, read_cache: bool = True) -> horizons.HorizonMap:
    """The horizon map of ``mesh`` at ``[sun] horizon_azimuths`` (default
    :data:`crater_thermal.horizons.DEFAULT_N_AZIMUTHS`), read from or written to the cache folder.
    ``progress``: optional ``(done, total)`` callback (facets traced); ``read_cache``: False to trace
    without looking in the cache (see :func:`crater_thermal.horizons.horizon_map`)."""
    return horizons.horizon_map(
        mesh,
        tracer,
        n_azimuths=_n_azimuths(sun),
        cache_dir=cache.folder("horizons"),
        progress=progress,
        read_cache=read_cache,
    )


def cached_horizon_map(sun, mesh, tracer) -> Optional[horizons.HorizonMap]:
    """The horizon map :func:`horizon_map` would read from the cache folder, or None."""
    return horizons.cached(mesh, tracer, n_azimuths=_n_azimuths(sun), cache_dir=cache.folder("horizons"))


def _n_azimuths(sun) -> int:
    return sun.horizon_azimuths or horizons.DEFAULT_N_AZIMUTHS


def _no_timer(name: str):
    return contextlib.nullcontext()


def absorbed_sunlight(surface, mesh, sun_dirs, direct, scat, F):
    """Incident and absorbed sunlight [W m-2] with an incidence-dependent albedo for direct light.

    Direct sunlight is reflected with A(i) (``illumination.direct_albedo``, ``surface.albedo_model``);
    scattered light, which arrives from many directions, with the albedo A0 (``surface.albedo``, the
    normal-incidence value, a lower bound of the hemispherical average of A(i)). Radiosity:
    B = A(i) E + A0 F B, so the scattered irradiance is F (I - A0 F)^-1 A(i) E, computed with the A0
    solver on the equivalent direct flux A(i) E / A0. Returns ``(solar_incident, solar_absorbed)``,
    both (nt, nf): ``solar_absorbed = (1 - A(i)) E + (1 - A0) (solar_incident - E)``.
    """
    A0 = float(surface.albedo)
    A_dir = illumination.direct_albedo(
        mesh.normals, sun_dirs, A0, surface.albedo_model, surface.albedo_a, surface.albedo_b
    )
    if scat is None:
        scattered = np.zeros_like(direct)
    elif A0 > 0:
        equivalent = direct * (A_dir / A0)
        scattered = np.maximum(scat.solar_incident(equivalent) - equivalent, 0.0)
    else:  # no multiple scattering: one bounce of the directly reflected light
        scattered = np.asarray((F @ (A_dir * direct).T).T)
    solar = direct + scattered
    return solar, (1.0 - A_dir) * direct + (1.0 - A0) * scattered
