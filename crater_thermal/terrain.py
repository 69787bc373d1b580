"""Real sites: polar digital elevation models (DEMs) in, a site mesh out.

This is the only module that imports ``rasterio`` and ``pyproj``.

Reading
-------
Any raster GDAL reads goes through ``rasterio``: GeoTIFF, the LOLA polar products distributed as
PDS3 ``.IMG`` with a detached ``.LBL`` (GDAL's PDS driver; open the ``.LBL`` or the ``.IMG``), and
GMT/COARDS netCDF grids (``.grd``, ``.nc``; GDAL's netCDF driver). The raster must carry a projected
coordinate reference system (CRS) on the Moon (a body of radius 1737.4 km, within 1 %); its sphere is
the *reference sphere* of the site, of radius ``reference_radius_m`` (the CRS's semi-major axis;
1,737,400 m for every LOLA and IAU 2015 lunar CRS).

Heights. A pixel value ``v`` becomes ``v * scale + offset`` with the band's scale and offset (GDAL
reads ``SCALING_FACTOR`` and ``OFFSET`` from a PDS3 label, ``scale_factor``/``add_offset`` from
GeoTIFF tags), times 1000 if the band's unit is km. Three conventions exist and all are handled:

* ``"height"``: the value is the height above the reference sphere [m];
* ``"radius"``: the value is the distance from the Moon's centre [m] (LOLA's polar LDEM products:
  ``DN * 0.5 m + 1,737,400 m``); the height is ``radius - reference_radius_m``;
* ``"tangent"`` (curvature applied): the value ``z`` is the coordinate of the point along the up axis of
  a Cartesian frame tangent to the reference sphere at the projection's origin (the pole of a polar
  stereographic CRS), the point lying in the direction its map x/y give: ``z = (R + h) cos(theta) - R``
  with ``theta`` the angle between the point and the origin seen from the Moon's centre, hence
  ``h = (R + z) / cos(theta) - R``, about ``z + r**2 / (2 R)`` at a distance ``r`` from the origin
  (5.6 km at 140 km, where the approximation is within 10 m for |z| <= 5 km). python-flux's LOLA grids
  are of this kind.

``height_kind="auto"`` (the default) takes ``"radius"`` when the median valid value in the site
exceeds half the reference radius (a height of > 868 km is impossible on the Moon) and ``"height"``
otherwise (never ``"tangent"``: such a file must be declared); the choice is recorded in the mesh
metadata.

Overrides: saying what the file does not
-----------------------------------------
Real files often lack or misstate their metadata. :func:`open_dem` (and :func:`site_mesh`,
``mesh dem``, the ``[crater]`` keys of a case) take

* ``crs``: the CRS to use instead of the file's (or where it has none): a PROJ string, WKT, or an
  authority code such as ``IAU_2015:30135`` (the Moon's south polar stereographic, R = 1737.4 km);
* ``xy_units`` (``"m"`` or ``"km"``): the unit of the raster's x/y coordinates (its geotransform),
  whatever the CRS says; the geotransform is converted to the CRS's unit;
* ``z_units`` (``"m"`` or ``"km"``): the unit of the pixel values (after scale and offset), whatever
  the band's unit tag says;
* ``height_kind`` (above).

A file is refused with a one-line :class:`DEMError` that names these overrides (:data:`OVERRIDES_HINT`)
when its metadata cannot be right: no CRS; a geographic or non-lunar CRS (an Earth ellipsoid, a sphere
of 1.7 km: a radius in km written as metres); a polar projection of the other hemisphere than the site;
a site centre outside the raster, with the diagnosis when it would lie inside with the x/y read as km
(or as m); heights that only make sense in km (all within +-11, the Moon's relief in km, and a relief
below 1e-3 of the site's width; or values of 1737 +- 11: radii in km). The last two checks are
heuristics: an explicit ``z_units`` turns them off.

Meshing
-------
The site is the disk of (geodesic) radius ``radius_km`` about the centre (``center_lat_deg``,
``center_lon_deg``, planetocentric, east longitude), optionally surrounded by a coarser ring out to
``outer_radius_km`` that only casts shadows and exchanges radiation (its facets are not analysed).

* Nodes lie on an equilateral triangular lattice of edge ``resolution_m`` (``outer_resolution_m`` in
  the ring) in the azimuthal-equidistant plane of the centre (distances from the centre are true
  geodesic distances), plus one ring of nodes exactly on each boundary circle; the triangles are the
  Delaunay triangulation of those nodes (``scipy.spatial.Delaunay``). A facet of the inner region has
  an area of about ``0.433 resolution_m**2``; the inner disk holds about
  ``7.26 (radius / resolution)**2`` facets.
* Heights at the nodes are resampled from the DEM by GDAL (``rasterio.warp.reproject``): bilinear
  interpolation at the node positions, *not* averaged over the facet (the kernel is not widened when
  the mesh is coarser than the pixels), so that crests and peaks, which cast the shadows, keep their
  heights. Noise at the pixel scale is then sampled, not smoothed: to smooth a noisy DEM, resample it
  first (e.g. ``gdalwarp -r average``). An idealized 2 km crater meshed at 100 m keeps its floor depth
  to 0.01 m and its rim crest to ~2 m (with an averaging kernel the crest lost 5 m).
* Every node is placed at its true 3-D position on the Moon, ``(R + h) * u(lat, lon)``, and expressed
  in the local East-North-Up frame of the centre (x east, y north, z up; origin on the reference
  sphere below the centre; at a pole, north points along the meridian ``center_lon_deg``, as in
  :mod:`crater_thermal.ephemeris`). The curvature of the Moon is therefore in the geometry: 50 km from
  the centre the reference sphere lies ~0.72 km below the tangent plane and its facets tilt by ~1.65 deg.
* Inner facets come first: facets ``0 .. n_inner - 1`` are the inner region (all three nodes within
  ``radius_km``), the rest the outer ring. ``meta["n_inner"]`` records the split and travels with the
  mesh (PLY header) into ``run.nc`` (the per-facet ``inner`` flag).

Limits (checked before anything is read or written, one-line :class:`DEMError`): the raster must have
a CRS (its own or ``crs``) and a geotransform, the CRS must be projected, on the Moon, polar in the site's
hemisphere if polar at all, and undistorted at the site (scale
within 10 % of true: a non-polar projection far from its centre is refused), the whole site must lie
inside the raster and on valid (non-nodata) pixels, the resolution must lie between a tenth of the DEM
pixel and a third of the radius, and the estimated mesh (facets and memory, :func:`estimate_site`)
must stay within ``max_facets`` (default :data:`MAX_FACETS`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from crater_thermal import choices
from crater_thermal.errors import ConfigError, DEMError

__all__ = [
    "DEMInfo",
    "MAX_FACETS",
    "MESH_BYTES_PER_FACET",
    "HEIGHT_KINDS",
    "LENGTH_UNITS",
    "OVERRIDES_HINT",
    "open_dem",
    "estimate_site",
    "site_mesh",
    "enu_basis",
    "geographic_to_local",
    "local_to_geographic",
    "local_to_dem_xy",
    "dem_xy_to_local",
    "polar_crs",
    "synthetic_heights",
    "write_geotiff",
    "write_pds3",
    "read_heights",
]

#: Largest site mesh (inner + outer facets) :func:`site_mesh` builds without ``max_facets``.
MAX_FACETS = 2_000_000
#: Estimated peak memory of meshing per facet [bytes] (lattice, resampling grid, Delaunay, mesh caches;
#: measured ~300 B on a 200k-facet site, rounded up).
MESH_BYTES_PER_FACET = 400.0
#: Estimated memory of the exact view-factor matrix per facet pair that sees each other [bytes]
#: (value + index), with ~12 % of pairs visible on rough terrain; shown in the size estimate only.
VIEW_FACTOR_BYTES_PER_PAIR = 12.0
HEIGHT_KINDS = choices.HEIGHT_KINDS
#: Units the overrides ``xy_units`` / ``z_units`` may name, and their size [m].
LENGTH_UNITS = choices.LENGTH_UNITS
_UNIT_M = {"m": 1.0, "km": 1000.0}
#: Named by every refusal of a file's metadata: how to say what the file does not.
OVERRIDES_HINT = (
    "say what the file does not with mesh dem --crs CRS, --xy-units m|km, --z-units m|km, "
    "--height-kind auto|height|radius|tangent (case file: crater.crs, crater.xy_units, crater.z_units, "
    "crater.height_kind)"
)
#: Largest |height| on the Moon [km], rounded up (LOLA: -9.1 km in Antoniadi, +10.8 km near Engel'gardt):
#: pixel values all within this bound, read as metres, are suspected to be km.
_MOON_RELIEF_KM = 11.0
#: Relief of a site below this fraction of its width [m/m] is implausibly flat for lunar terrain: with
#: values within +-11, such heights are taken for km read as metres (0.06 deg mean slope).
_MIN_RELIEF_PER_WIDTH = 1e-3
#: Largest angle [deg] between a site and the origin of a "tangent" (curvature-applied) height frame.
_MAX_TANGENT_ANGLE_DEG = 30.0
#: Lunar reference radius [m] (IAU 2015 sphere; LOLA products) and the 1 % tolerance of a DEM's CRS.
MOON_RADIUS_M = 1_737_400.0
_BODY_TOLERANCE = 0.01
#: Largest accepted map-scale distortion at the site (|k - 1|, per axis).
MAX_SCALE_DISTORTION = 0.10
#: Facets of the equilateral lattice per unit (radius / edge)**2 of a disk: 4 pi / sqrt(3).
_FACETS_PER_DISK = 4.0 * math.pi / math.sqrt(3.0)


def _libs():
    """Import rasterio and pyproj, or a one-line error naming the extra to install."""
    try:
        import pyproj
        import rasterio
        import rasterio.warp  # noqa: F401
    except ImportError as exc:  # pragma: no cover - both are in the 'sites' and 'test' extras
        raise DEMError(f"reading DEMs needs rasterio and pyproj ({exc}); pip install 'crater_thermal[sites]'") from None
    return rasterio, pyproj


# ---------------------------------------------------------------------------------------- frames


def enu_basis(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Local East-North-Up unit vectors in body-fixed coordinates (same convention as the ephemeris).

    Parameters
    ----------
    lat_deg, lon_deg : float [deg]
        Planetocentric latitude and east longitude of the centre.

    Returns
    -------
    B : (3, 3) float
        Rows east, north, up: ``v_enu = B @ v_body``. At a pole, north points along the meridian
        ``lon_deg`` (the limit along that meridian).
    """
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sp, cp, sl, cl = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    if abs(lat_deg) == 90.0:
        cp = 0.0
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def _unit_vectors(lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    return np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)


def _centre(meta: dict) -> tuple[float, float, float]:
    try:
        return float(meta["center_lat_deg"]), float(meta["center_lon_deg"]), float(meta["reference_radius_m"])
    except (KeyError, TypeError, ValueError):
        raise DEMError(
            "mesh metadata has no site centre (center_lat_deg, center_lon_deg, reference_radius_m): not a DEM site mesh"
        ) from None


def geographic_to_local(lat_deg, lon_deg, height_m, meta: dict) -> np.ndarray:
    """Points given by latitude, longitude [deg] and height above the reference sphere [m] in the site frame.

    Returns
    -------
    (..., 3) float [m]
        East, north, up coordinates relative to the point of the reference sphere below the centre.
    """
    lat0, lon0, R = _centre(meta)
    u = _unit_vectors(np.asarray(lat_deg, float), np.asarray(lon_deg, float))
    p = (R + np.asarray(height_m, float))[..., None] * u - R * _unit_vectors(np.array(lat0), np.array(lon0))
    return p @ enu_basis(lat0, lon0).T


def local_to_geographic(points, meta: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`geographic_to_local`: site-frame points [m] to (lat_deg, lon_deg, height_m)."""
    lat0, lon0, R = _centre(meta)
    pts = np.asarray(points, float)
    body = pts @ enu_basis(lat0, lon0) + R * _unit_vectors(np.array(lat0), np.array(lon0))
    r = np.linalg.norm(body, axis=-1)
    lat = np.degrees(np.arcsin(np.clip(body[..., 2] / r, -1.0, 1.0)))
    lon = np.degrees(np.arctan2(body[..., 1], body[..., 0]))
    return lat, lon, r - R


def _transformer(crs_from, crs_to):
    _, pyproj = _libs()
    return pyproj.Transformer.from_crs(crs_from, crs_to, always_xy=True)


def local_to_dem_xy(points, meta: dict) -> tuple[np.ndarray, np.ndarray]:
    """Site-frame points [m] to the DEM's projected coordinates (x, y) [CRS units, m for lunar CRSs].

    Used for plan-view maps in the DEM's own coordinates. Needs ``meta["crs_wkt"]``.
    """
    _, pyproj = _libs()
    crs = pyproj.CRS.from_wkt(meta["crs_wkt"])
    lat, lon, _ = local_to_geographic(points, meta)
    return _transformer(crs.geodetic_crs, crs).transform(lon, lat)


def dem_xy_to_local(x, y, height_m, meta: dict) -> np.ndarray:
    """DEM projected coordinates and heights to site-frame points [m] (inverse of :func:`local_to_dem_xy`)."""
    _, pyproj = _libs()
    crs = pyproj.CRS.from_wkt(meta["crs_wkt"])
    lon, lat = _transformer(crs, crs.geodetic_crs).transform(np.asarray(x, float), np.asarray(y, float))
    return geographic_to_local(lat, lon, height_m, meta)


def polar_crs(lat_deg: float):
    """The IAU 2015 lunar polar stereographic CRS of the hemisphere of ``lat_deg`` (pyproj CRS).

    South: ``IAU_2015:30135`` (``+proj=stere +lat_0=-90 +lon_0=0 +k=1 +R=1737400``, true scale at the
    pole, as LOLA's polar products); north: ``IAU_2015:30130``.
    """
    _, pyproj = _libs()
    return pyproj.CRS("IAU_2015:30135" if lat_deg < 0 else "IAU_2015:30130")


# ------------------------------------------------------------------------------------ DEM opening


@dataclass(frozen=True)
class DEMInfo:
    """What a DEM file says about itself, with the caller's overrides applied (nothing is read from the pixels).

    Attributes
    ----------
    path : Path
        The DEM file.
    crs_wkt : str
        The CRS used (WKT): the file's, or the ``crs`` override.
    transform : tuple of 6 float
        Affine pixel -> map (a, b, c, d, e, f) [CRS units per pixel], after ``xy_units``.
    width, height : int
        Raster size [pixels].
    nodata : float or None
        Raw nodata value.
    scale, offset : float
        value = raw * scale + offset (before the unit factor).
    unit_factor : float
        1 for metres, 1000 for km (the band's unit tag, or ``z_units``).
    reference_radius_m : float
        Semi-major axis of the CRS's body [m].
    pixel_m : float
        Nominal pixel size [m] (map units times the CRS's linear unit).
    driver : str
        The GDAL driver that read the file.
    origin_lat_deg, origin_lon_deg : float
        The projection's origin [deg] (where map x, y = false easting, northing; the pole of a polar
        stereographic CRS): the tangent point of "tangent" heights.
    overrides : dict
        The overrides given (``crs``, ``xy_units``, ``z_units``), for the mesh metadata.
    """

    path: Path
    crs_wkt: str
    transform: tuple
    width: int
    height: int
    nodata: Optional[float]
    scale: float
    offset: float
    unit_factor: float
    reference_radius_m: float
    pixel_m: float
    driver: str
    origin_lat_deg: float = float("nan")
    origin_lon_deg: float = float("nan")
    overrides: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.path.name


def _parse_crs(text):
    """A pyproj CRS from the ``crs`` override (PROJ string, WKT or authority code), or a one-line error."""
    _, pyproj = _libs()
    if not isinstance(text, str) or not text.strip():
        raise ConfigError(f"crs = {text!r} must be a PROJ string, WKT or an authority code such as IAU_2015:30135")
    try:
        return pyproj.CRS.from_user_input(text.strip())
    except pyproj.exceptions.CRSError as exc:
        shown = text.strip() if len(text.strip()) <= 80 else text.strip()[:77] + "..."
        reason = " ".join(str(exc).split())
        raise DEMError(
            f"crs = {shown!r} is not a coordinate reference system pyproj knows ({reason[:160]}): give a PROJ "
            "string (+proj=stere +lat_0=-90 +lon_0=0 +R=1737400), WKT, or an authority code such as "
            "IAU_2015:30135 (Moon south polar stereographic) or IAU_2015:30130 (north)"
        ) from None


def _axis_metres(pcrs) -> float:
    """Size of the CRS's linear unit [m] (1 for metres, 1000 for km)."""
    return float(pcrs.axis_info[0].unit_conversion_factor) if pcrs.axis_info else 1.0


def _projection_origin(pcrs) -> tuple[float, float]:
    """(lat_deg, lon_deg) of the point whose map coordinates are the false easting and northing."""
    fe = fn = 0.0
    try:
        for prm in pcrs.coordinate_operation.params:
            name = prm.name.lower()
            if "easting" in name:
                fe = float(prm.value) * float(prm.unit_conversion_factor)
            elif "northing" in name:
                fn = float(prm.value) * float(prm.unit_conversion_factor)
        k = _axis_metres(pcrs)
        lon, lat = _transformer(pcrs, pcrs.geodetic_crs).transform(fe / k, fn / k)
        return float(lat), float(lon)
    except Exception:  # pyproj raises several kinds on unusual CRSs; the origin is then unknown (NaN)
        return float("nan"), float("nan")


def _unit_override(name: str, value) -> Optional[str]:
    if value is None:
        return None
    if value not in LENGTH_UNITS:
        what = "x/y coordinates (geotransform)" if name == "xy_units" else "pixel values (heights)"
        raise ConfigError(
            f"{name} = {value!r} must be one of {', '.join(LENGTH_UNITS)}: the unit of the raster's {what}"
        )
    return value


def open_dem(path, crs=None, xy_units: Optional[str] = None, z_units: Optional[str] = None) -> DEMInfo:
    """Open a DEM and check its georeferencing (header only), with the caller's overrides.

    Parameters
    ----------
    path : path-like
        GeoTIFF, GMT/COARDS netCDF grid, or any raster GDAL reads; for PDS3 products the ``.LBL`` (or the
        ``.IMG`` beside it).
    crs : str or None
        CRS to use instead of the file's (PROJ string, WKT, or an authority code such as
        ``IAU_2015:30135``); None: the file's.
    xy_units : {"m", "km"} or None
        Unit of the raster's x/y coordinates (its geotransform) [m or km]; None: the CRS's unit.
    z_units : {"m", "km"} or None
        Unit of the pixel values after scale and offset; None: the band's unit tag (metres if none).

    Raises
    ------
    DEMError
        Missing/unreadable file; no CRS; no geotransform; geographic CRS (degrees); a CRS not on the Moon;
        an unknown ``crs``. The message names the overrides (:data:`OVERRIDES_HINT`).
    ConfigError
        ``xy_units`` / ``z_units`` not one of :data:`LENGTH_UNITS`.
    """
    rasterio, pyproj = _libs()
    xy_units = _unit_override("xy_units", xy_units)
    z_units = _unit_override("z_units", z_units)
    p = Path(path)
    if not p.is_file():
        raise DEMError(f"DEM file {str(p)!r} does not exist")
    given = crs is not None
    pcrs = _parse_crs(crs) if given else None
    try:
        with rasterio.open(p) as src:
            file_crs, tr = src.crs, src.transform
            width, height, driver = src.width, src.height, src.driver
            nodata = src.nodata
            scale = float(src.scales[0]) if src.scales and src.scales[0] is not None else 1.0
            offset = float(src.offsets[0]) if src.offsets and src.offsets[0] is not None else 0.0
            unit = (src.units[0] or "") if src.units else ""
            count = src.count
    except rasterio.errors.RasterioError as exc:
        raise DEMError(f"cannot read DEM {str(p)!r}: {' '.join(str(exc).split())}") from None
    if count < 1:
        raise DEMError(f"DEM {p.name!r} has no raster band")
    if not given:
        if file_crs is None or not file_crs.to_wkt():
            raise DEMError(
                f"DEM {p.name!r} has no coordinate reference system (no CRS in the file or its label): "
                "cannot place it on the Moon; give one, e.g. --crs IAU_2015:30135 (crater.crs) for a south "
                f"polar stereographic grid; {OVERRIDES_HINT}"
            )
        pcrs = pyproj.CRS.from_wkt(file_crs.to_wkt())
    whose = f"crs = {crs!r}" if given else f"DEM {p.name!r} CRS"
    if tr.is_identity:
        raise DEMError(f"DEM {p.name!r} has no geotransform (pixel to map coordinates): cannot locate its pixels")
    if pcrs.is_geographic or not pcrs.is_projected:
        raise DEMError(
            f"{whose} is a geographic CRS ({pcrs.name}, degrees): meshing needs a projected CRS, e.g. lunar "
            f"polar stereographic IAU_2015:30135; {OVERRIDES_HINT}"
        )
    a = float(pcrs.ellipsoid.semi_major_metre) if pcrs.ellipsoid else float("nan")
    if not (abs(a - MOON_RADIUS_M) <= _BODY_TOLERANCE * MOON_RADIUS_M):
        hint = " (a radius in km given as metres?)" if abs(a - MOON_RADIUS_M / 1e3) <= _BODY_TOLERANCE * a else ""
        raise DEMError(
            f"{whose} ({pcrs.name}) is on a body of radius {a / 1e3:.4g} km{hint}, not the Moon "
            f"({MOON_RADIUS_M / 1e3:.1f} km): give a lunar CRS, e.g. --crs IAU_2015:30135 (crater.crs); "
            f"{OVERRIDES_HINT}"
        )
    crs_m = _axis_metres(pcrs)
    if xy_units is not None:
        k = _UNIT_M[xy_units] / crs_m
        tr = rasterio.Affine(tr.a * k, tr.b * k, tr.c * k, tr.d * k, tr.e * k, tr.f * k)
    if z_units is not None:
        unit_factor = _UNIT_M[z_units]
    else:
        unit_l = unit.strip().lower()
        unit_factor = 1000.0 if unit_l in ("km", "kilometer", "kilometers", "kilometre", "kilometres") else 1.0
    o_lat, o_lon = _projection_origin(pcrs)
    overrides = {k: v for k, v in (("crs", crs), ("xy_units", xy_units), ("z_units", z_units)) if v is not None}
    return DEMInfo(
        path=p.resolve(),
        crs_wkt=pcrs.to_wkt(),
        transform=tuple(tr)[:6],
        width=int(width),
        height=int(height),
        nodata=None if nodata is None else float(nodata),
        scale=scale,
        offset=offset,
        unit_factor=unit_factor,
        reference_radius_m=a,
        pixel_m=float(math.sqrt(abs(tr.a * tr.e - tr.b * tr.d))) * crs_m,
        driver=str(driver),
        origin_lat_deg=o_lat,
        origin_lon_deg=o_lon,
        overrides=overrides,
    )


# --------------------------------------------------------------------------------- site planning


def _number(name: str, value, lo: float, hi: float) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not (math.isfinite(x) and lo <= x <= hi):
        raise ConfigError(f"{name} = {value!r} is outside the allowed range [{lo:g}, {hi:g}]")
    return x


def estimate_site(
    radius_km: float,
    resolution_m: float,
    outer_radius_km: Optional[float] = None,
    outer_resolution_m: Optional[float] = None,
) -> dict:
    """Facet counts and memory of a site mesh, before building it.

    Returns
    -------
    dict
        ``n_inner``, ``n_outer``, ``n_facets`` (estimates, within a few %), ``mesh_bytes`` (meshing
        peak, :data:`MESH_BYTES_PER_FACET` per facet) and ``view_factor_bytes`` (the exact matrix with
        ~12 % of facet pairs visible).
    """
    R, H = radius_km * 1e3, resolution_m
    n_in = _FACETS_PER_DISK * (R / H) ** 2
    n_out = 0.0
    if outer_radius_km:
        n_out = _FACETS_PER_DISK * ((outer_radius_km * 1e3) ** 2 - R * R) / outer_resolution_m**2
    n = n_in + n_out
    return {
        "n_inner": n_in,
        "n_outer": n_out,
        "n_facets": n,
        "mesh_bytes": n * MESH_BYTES_PER_FACET,
        "view_factor_bytes": 0.12 * n * n * VIEW_FACTOR_BYTES_PER_PAIR,
    }


def _scale_factors(crs, lat_deg: float, lon_deg: float) -> tuple[float, float]:
    _, pyproj = _libs()
    f = pyproj.Proj(crs).get_factors(lon_deg, lat_deg)
    return float(f.meridional_scale), float(f.parallel_scale)


def _aeqd(geodetic_crs, lat_deg: float, lon_deg: float):
    _, pyproj = _libs()
    from pyproj.crs import ProjectedCRS
    from pyproj.crs.coordinate_operation import AzimuthalEquidistantConversion

    conv = AzimuthalEquidistantConversion(latitude_natural_origin=lat_deg, longitude_natural_origin=lon_deg)
    return ProjectedCRS(conversion=conv, geodetic_crs=geodetic_crs)


def _outside_diagnosis(info: DEMInfo, crs, aeqd) -> str:
    """Why the site centre may fall off the raster: its map x, y against the raster's extent, and whether it
    would fall inside with the raster's x/y read in km (or in m) instead; ends with the overrides."""
    rasterio, _ = _libs()
    tr = rasterio.Affine(*info.transform)
    x, y = (float(v) for v in _transformer(aeqd, crs).transform(0.0, 0.0))
    unit = _axis_metres(crs)
    corners = [tr @ (c, r) for c, r in ((0, 0), (info.width, 0), (0, info.height), (info.width, info.height))]
    xs, ys = [c[0] for c in corners], [c[1] for c in corners]

    def inside(k: float) -> bool:  # raster coordinates scaled by k
        return min(xs) * k <= x <= max(xs) * k and min(ys) * k <= y <= max(ys) * k

    km = unit / 1e3
    text = (
        f"the centre is at map x, y = {x * km:.6g}, {y * km:.6g} km, the raster ({info.width} x {info.height} "
        f"pixels of {info.pixel_m:g} m) spans x {min(xs) * km:.6g} to {max(xs) * km:.6g} km, y "
        f"{min(ys) * km:.6g} to {max(ys) * km:.6g} km"
    )
    if "xy_units" not in info.overrides:
        if inside(1000.0):
            text += "; it would contain the centre with its x/y in km, not m: pass --xy-units km (crater.xy_units)"
        elif inside(1e-3):
            text += "; it would contain the centre with its x/y in m, not km: pass --xy-units m (crater.xy_units)"
    return f"{text}; move the site, or if the file's metadata is wrong, {OVERRIDES_HINT}"


def _footprint_check(info: DEMInfo, crs, aeqd, radius_m: float, margin_m: float, what: str) -> None:
    """Refuse a site (disk of ``radius_m``, plus the resampling grid's ``margin_m``, in the aeqd plane) that
    reaches beyond the raster's pixel centres."""
    rasterio, _ = _libs()
    tr = rasterio.Affine(*info.transform)
    inv = ~tr
    az = np.linspace(0.0, 2.0 * np.pi, 181)[:-1]
    radii = np.linspace(0.0, radius_m + margin_m, 401)
    rr, aa = np.meshgrid(radii, az, indexing="ij")
    to_dem = _transformer(aeqd, crs)
    x, y = to_dem.transform((rr * np.sin(aa)).ravel(), (rr * np.cos(aa)).ravel())
    x, y = np.asarray(x), np.asarray(y)
    col = (inv.a * x + inv.b * y + inv.c).reshape(rr.shape)
    row = (inv.d * x + inv.e * y + inv.f).reshape(rr.shape)
    inside = (col >= 0.5) & (col <= info.width - 0.5) & (row >= 0.5) & (row <= info.height - 0.5)
    inside &= np.isfinite(col) & np.isfinite(row)
    if not inside[0].all():
        raise DEMError(f"site centre lies outside DEM {info.name!r}: {_outside_diagnosis(info, crs, aeqd)}")
    if not inside.all():
        ok = np.all(inside, axis=1)
        fit = max(0.0, radii[np.argmin(ok) - 1] - margin_m)
        raise DEMError(
            f"site reaches beyond the edge of DEM {info.name!r}: {what} {radius_m / 1e3:g} km, "
            f"at most {math.floor(fit / 100.0) / 10.0:g} km fits about this centre"
        )


def _check_site(
    info: DEMInfo, lat: float, lon: float, R: float, H: float, R2: Optional[float], H2: Optional[float], max_facets: int
) -> dict:
    """All checks that need no pixel: distortion, resolutions, size, footprint."""
    _, pyproj = _libs()
    crs = pyproj.CRS.from_wkt(info.crs_wkt)
    o_lat = info.origin_lat_deg
    if abs(o_lat) > 89.0 and lat * o_lat < 0.0:
        pole, other = ("north", "south") if o_lat > 0 else ("south", "north")
        raise DEMError(
            f"DEM {info.name!r} CRS ({crs.name}) is a {pole}-polar projection (origin at lat {o_lat:g}), but "
            f"the site is at lat {lat:g}: a {other}-polar grid labelled with the wrong pole? pass --crs "
            f"{'IAU_2015:30135' if lat < 0 else 'IAU_2015:30130'} (crater.crs); {OVERRIDES_HINT}"
        )
    h, k = _scale_factors(crs, lat, lon)
    if not (abs(h - 1.0) <= MAX_SCALE_DISTORTION and abs(k - 1.0) <= MAX_SCALE_DISTORTION):
        raise DEMError(
            f"DEM {info.name!r} CRS ({crs.name}) is not a projection for a site at lat {lat:g}, "
            f"lon {lon:g}: its map scale there is {h:.3g} x {k:.3g} (more than "
            f"{MAX_SCALE_DISTORTION:.0%} off; a non-polar projection far from its centre): use a polar "
            f"stereographic DEM, or if the file's CRS is wrong, {OVERRIDES_HINT}"
        )
    ground_px = info.pixel_m / math.sqrt(h * k)
    if H < ground_px / 10.0:
        raise DEMError(
            f"resolution_m = {H:g} is absurd for DEM {info.name!r}: finer than a tenth of its "
            f"{ground_px:.3g} m pixels (the mesh would only interpolate); use >= {ground_px / 10.0:.3g} m"
        )
    if H > R / 3.0:
        raise DEMError(
            f"resolution_m = {H:g} is too coarse for radius_km = {R / 1e3:g}: at most a third of the "
            f"radius ({R / 3.0:.4g} m)"
        )
    if R2 is not None:
        if H2 < H:
            raise DEMError(f"outer_resolution_m = {H2:g} must be >= resolution_m = {H:g}")
        if H2 > (R2 - R):
            raise DEMError(
                f"outer_resolution_m = {H2:g} is wider than the outer ring ({(R2 - R) / 1e3:g} km): "
                "enlarge outer_radius_km or refine outer_resolution_m"
            )
    est = estimate_site(R / 1e3, H, None if R2 is None else R2 / 1e3, H2)
    if est["n_facets"] > max_facets:
        scale = math.sqrt(est["n_facets"] / (0.9 * max_facets))
        raise DEMError(
            f"site too large: ~{est['n_facets']:.3g} facets (~{est['mesh_bytes'] / 1e9:.3g} GB to mesh, "
            f"~{est['view_factor_bytes'] / 1e9:.3g} GB of exact view factors), limit {max_facets:.3g} "
            f"facets: use resolution_m >= {H * scale:.4g}"
            + (f" (and outer_resolution_m >= {H2 * scale:.4g})" if H2 else "")
            + " or a smaller radius"
        )
    aeqd = _aeqd(crs.geodetic_crs, lat, lon)
    _footprint_check(
        info,
        crs,
        aeqd,
        R2 if R2 is not None else R,
        H2 if R2 is not None else H,
        "outer_radius_km" if R2 is not None else "radius_km",
    )
    est["ground_pixel_m"] = ground_px
    est["crs"], est["aeqd"] = crs, aeqd
    return est


# ---------------------------------------------------------------------------------- resampling


def _resample(
    info: DEMInfo, aeqd, x0: float, y0: float, dx: float, dy: float, nx: int, ny: int, **warp_options
) -> np.ndarray:
    """Raw DEM values (scale/offset applied, metres) on a regular aeqd grid of pixel centres.

    The grid's pixel (i, j) (row i from the top) is centred at ``(x0 + j dx, y0 - i dy)``. Bilinear
    resampling by GDAL (a warped virtual raster of the file, streamed, with the CRS and geotransform of
    ``info``: the overrides apply); nodata and points off the raster come back as NaN.
    """
    rasterio, _ = _libs()
    from rasterio.enums import Resampling
    from rasterio.vrt import WarpedVRT

    dst_tr = rasterio.Affine(dx, 0.0, x0 - 0.5 * dx, 0.0, -dy, y0 + 0.5 * dy)
    nodata = {} if info.nodata is None else {"src_nodata": info.nodata}
    with rasterio.open(info.path) as src:
        with WarpedVRT(
            src,
            src_crs=rasterio.crs.CRS.from_wkt(info.crs_wkt),
            src_transform=rasterio.Affine(*info.transform),
            crs=rasterio.crs.CRS.from_wkt(aeqd.to_wkt()),
            transform=dst_tr,
            width=nx,
            height=ny,
            resampling=Resampling.bilinear,
            nodata=np.nan,
            dtype="float64",
            XSCALE=1,
            YSCALE=1,
            **nodata,
            **warp_options,
        ) as vrt:
            dst = vrt.read(1)
    return (dst * info.scale + info.offset) * info.unit_factor


def _lattice(R: float, H: float, r_min: float = -1.0) -> tuple[np.ndarray, np.ndarray]:
    """Equilateral-lattice nodes of edge H with r_min < r <= R - H/2, as (points (n, 2), (row, col) indices).

    Row j lies at ``y = j H sqrt(3)/2``; its nodes at ``x = (i + (j mod 2)/2) H``; in a grid of spacing
    (H/2, H sqrt(3)/2) they are the cells with ``col = 2 i + (j mod 2)``.
    """
    dy = H * math.sqrt(3.0) / 2.0
    nj = int(math.floor(R / dy))
    ni = int(math.floor(R / H)) + 1
    j = np.arange(-nj, nj + 1)
    i = np.arange(-ni, ni + 1)
    J, Ii = np.meshgrid(j, i, indexing="ij")
    col2 = 2 * Ii + (J % 2)  # x in units of H/2
    x = col2 * (0.5 * H)
    y = J * dy
    r = np.hypot(x, y)
    keep = (r <= R - 0.5 * H) & (r > r_min)
    return np.stack([x[keep], y[keep]], axis=1), np.stack([J[keep], col2[keep]], axis=1)


def _circle(R: float, H: float) -> np.ndarray:
    n = max(12, int(math.ceil(2.0 * math.pi * R / H)))
    a = (np.arange(n) + 0.5) * (2.0 * math.pi / n)
    return np.stack([R * np.sin(a), R * np.cos(a)], axis=1)


def _heights_at(info: DEMInfo, aeqd, H: float, R: float, lattice_idx: np.ndarray, extra: np.ndarray) -> tuple:
    """Heights [raw DEM value, m] at lattice nodes (exact grid cells) and at extra points (bilinear on the grid)."""
    from scipy.ndimage import map_coordinates

    dx, dy = 0.5 * H, H * math.sqrt(3.0) / 2.0
    nj = int(math.floor(R / dy)) + 1
    nc = int(math.floor(R / dx)) + 2
    grid = _resample(info, aeqd, -nc * dx, nj * dy, dx, dy, 2 * nc + 1, 2 * nj + 1)
    rows = nj - lattice_idx[:, 0]
    cols = nc + lattice_idx[:, 1]
    at_nodes = grid[rows, cols]
    er = nj - extra[:, 1] / dy
    ec = nc + extra[:, 0] / dx
    at_extra = map_coordinates(grid, [er, ec], order=1, mode="nearest", prefilter=False)
    return at_nodes, at_extra


# ---------------------------------------------------------------------------------------- meshing


def _check_height_units(info: DEMInfo, raw: np.ndarray, width_m: float) -> None:
    """Refuse pixel values that only make sense in km (heights or radii read as metres); see the module
    docstring. Skipped when ``z_units`` was given."""
    if "z_units" in info.overrides or info.unit_factor != 1.0 or raw.size == 0:
        return
    lo, hi = float(np.min(raw)), float(np.max(raw))
    r_km = info.reference_radius_m / 1e3
    if max(abs(lo), abs(hi)) <= _MOON_RELIEF_KM and 0.0 < hi - lo < _MIN_RELIEF_PER_WIDTH * width_m:
        what = f"span only {hi - lo:.3g} m ({lo:.4g} to {hi:.4g}) over a site {width_m / 1e3:g} km wide"
        guess = "heights in km read as metres"
    elif abs(lo - r_km) <= _MOON_RELIEF_KM and abs(hi - r_km) <= _MOON_RELIEF_KM:
        what = f"lie between {lo:.6g} and {hi:.6g}"
        guess = f"radii in km (the Moon's is {r_km:g} km) read as metres"
    else:
        return
    raise DEMError(
        f"DEM {info.name!r} values {what}: they look like {guess}; pass --z-units km (crater.z_units = "
        f'"km"), or --z-units m if they really are metres; {OVERRIDES_HINT}'
    )


def _tangent_to_height(z: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray, info: DEMInfo) -> np.ndarray:
    """Heights above the reference sphere [m] of "tangent" (curvature-applied) values ``z`` [m].

    ``z = (R + h) cos(theta) - R``: the coordinate along the up axis of the frame tangent to the sphere at
    the projection's origin of the point in the direction (lat_deg, lon_deg) [deg], ``theta`` its angle
    from the origin at the Moon's centre; returns ``h = (R + z) / cos(theta) - R``.
    """
    R = info.reference_radius_m
    if not (math.isfinite(info.origin_lat_deg) and math.isfinite(info.origin_lon_deg)):
        raise DEMError(
            f"height_kind = 'tangent' needs the projection's origin, and the CRS of DEM {info.name!r} has none "
            f"that pyproj can compute; {OVERRIDES_HINT}"
        )
    u0 = _unit_vectors(np.array(info.origin_lat_deg), np.array(info.origin_lon_deg))
    cos_t = _unit_vectors(np.asarray(lat_deg, float), np.asarray(lon_deg, float)) @ u0
    worst = float(np.degrees(np.arccos(np.clip(np.min(cos_t), -1.0, 1.0))))
    if worst > _MAX_TANGENT_ANGLE_DEG:
        raise DEMError(
            f"height_kind = 'tangent': the site reaches {worst:.3g} deg from the projection's origin (lat "
            f"{info.origin_lat_deg:g}, lon {info.origin_lon_deg:g}) of DEM {info.name!r}, more than "
            f"{_MAX_TANGENT_ANGLE_DEG:g} deg: not a curvature-applied grid about that origin; {OVERRIDES_HINT}"
        )
    return (R + np.asarray(z, float)) / cos_t - R


def site_mesh(
    path,
    center_lat_deg: float,
    center_lon_deg: float,
    radius_km: float,
    resolution_m: Optional[float] = None,
    outer_radius_km: Optional[float] = None,
    outer_resolution_m: Optional[float] = None,
    height_kind: str = "auto",
    max_facets: int = MAX_FACETS,
    progress: Optional[Callable[[str], None]] = None,
    crs: Optional[str] = None,
    xy_units: Optional[str] = None,
    z_units: Optional[str] = None,
):
    """Mesh a site of a DEM (see the module docstring for the construction and the frame).

    Parameters
    ----------
    path : path-like
        DEM (GeoTIFF, PDS3 .LBL/.IMG, GMT/COARDS netCDF .grd, any GDAL raster) with a projected lunar CRS
        (its own, or ``crs``).
    center_lat_deg, center_lon_deg : float [deg]
        Site centre, planetocentric latitude and east longitude.
    radius_km : float [km]
        Radius of the analysed (inner) region, (0, 500].
    resolution_m : float or None [m]
        Facet edge in the inner region; default: the DEM's ground pixel or the edge giving ~10,000 inner
        facets, whichever is coarser.
    outer_radius_km, outer_resolution_m : float or None [km], [m]
        Optional coarser ring (shadows and radiation from distant terrain) out to ``outer_radius_km``
        (> radius_km) at ``outer_resolution_m`` (>= resolution_m; default 4 x resolution_m).
    height_kind : {"auto", "height", "radius", "tangent"}
        How to read the pixel values (see the module docstring).
    max_facets : int
        Refuse sites estimated above this many facets.
    progress : callable(str) or None
        Called with a short message at each stage.
    crs, xy_units, z_units : str or None
        Overrides of the file's metadata (see :func:`open_dem`): CRS (PROJ/WKT/authority code), unit of
        the x/y coordinates and of the pixel values ("m" or "km").

    Returns
    -------
    geometry.Mesh
        ``meta``: kind "dem", dem_source (file name), dem_path, crs_wkt, crs_name, center_lat_deg,
        center_lon_deg, reference_radius_m, radius_km, resolution_m, outer_radius_km, outer_resolution_m,
        height_kind, height_scale, height_offset, dem_pixel_m, dem_overrides (the overrides given),
        n_facets, n_inner, n_vertices, frame; with height_kind "tangent" also tangent_origin_lat_deg,
        tangent_origin_lon_deg.

    Raises
    ------
    DEMError, ConfigError
        See the module docstring ("Limits", "Overrides"); nothing is written.
    """
    from scipy.spatial import Delaunay

    from crater_thermal.geometry import Mesh

    say = progress or (lambda msg: None)
    lat = _number("center_lat_deg", center_lat_deg, -90.0, 90.0)
    lon = _number("center_lon_deg", center_lon_deg, -360.0, 360.0)
    R = _number("radius_km", radius_km, 1e-3, 500.0) * 1e3
    if height_kind not in HEIGHT_KINDS:
        raise ConfigError(f"height_kind = {height_kind!r} must be one of {', '.join(HEIGHT_KINDS)}")
    R2 = H2 = None
    if outer_radius_km is not None:
        R2 = _number("outer_radius_km", outer_radius_km, 0.0, 1000.0) * 1e3
        if R2 <= R:
            raise ConfigError(f"outer_radius_km = {outer_radius_km!r} must exceed radius_km = {radius_km!r}")
    elif outer_resolution_m is not None:
        raise ConfigError("outer_resolution_m needs outer_radius_km")
    info = open_dem(path, crs=crs, xy_units=xy_units, z_units=z_units)
    if resolution_m is None:
        H = max(info.pixel_m, R * math.sqrt(_FACETS_PER_DISK / 10_000.0))
    else:
        H = _number("resolution_m", resolution_m, 0.0, 1e6)
        if H <= 0.0:
            raise DEMError(f"resolution_m = {resolution_m!r} is absurd: must be > 0")
    if R2 is not None:
        H2 = 4.0 * H if outer_resolution_m is None else _number("outer_resolution_m", outer_resolution_m, 0.0, 1e6)
    plan = _check_site(info, lat, lon, R, H, R2, H2, int(max_facets))
    crs, aeqd = plan["crs"], plan["aeqd"]

    say("resampling DEM")
    pts_in, idx_in = _lattice(R, H)
    circ_in = _circle(R, H)
    v_in, v_circ = _heights_at(info, aeqd, H, R, idx_in, circ_in)
    parts_xy = [pts_in, circ_in]
    parts_v = [v_in, v_circ]
    n_inner_nodes = len(pts_in) + len(circ_in)
    if R2 is not None:
        pts_out, idx_out = _lattice(R2, H2, r_min=R + 0.5 * H2)
        circ_out = _circle(R2, H2)
        v_out, v_circ2 = _heights_at(info, aeqd, H2, R2, idx_out, circ_out)
        parts_xy += [pts_out, circ_out]
        parts_v += [v_out, v_circ2]
    xy = np.concatenate(parts_xy)
    raw = np.concatenate(parts_v)
    bad = ~np.isfinite(raw)
    if bad.any():
        k = int(np.argmax(bad))
        where = "inner region" if k < n_inner_nodes else "outer ring"
        lon_b, lat_b = _transformer(aeqd, crs.geodetic_crs).transform(xy[k, 0], xy[k, 1])
        raise DEMError(
            f"DEM {info.name!r} has nodata holes in the site: {int(bad.sum())} of {len(raw)} mesh nodes "
            f"({bad.mean():.1%}) fall on nodata, first in the {where} near lat {lat_b:.4f}, lon "
            f"{lon_b:.4f}; fill the holes or move/shrink the site"
        )
    kind = height_kind
    if kind == "auto":
        kind = "radius" if float(np.median(raw)) > 0.5 * info.reference_radius_m else "height"
    _check_height_units(info, raw, 2.0 * (R2 if R2 is not None else R))
    lon_n, lat_n = (np.asarray(v) for v in _transformer(aeqd, crs.geodetic_crs).transform(xy[:, 0], xy[:, 1]))
    Rref = info.reference_radius_m
    if kind == "radius":
        heights = raw - Rref
    elif kind == "tangent":
        heights = _tangent_to_height(raw, lat_n, lon_n, info)
    else:
        heights = raw
    if np.abs(heights).max() > 0.02 * Rref:
        raise DEMError(
            f"DEM {info.name!r} heights reach {np.abs(heights).max() / 1e3:.0f} km from the reference "
            f"sphere (read as {kind!r}): wrong height_kind, z_units, scale or offset? {OVERRIDES_HINT}"
        )

    say("triangulating")
    tri = Delaunay(xy)
    F = np.asarray(tri.simplices, dtype=np.int64)
    p = xy[F]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    signed = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
    F[signed < 0] = F[signed < 0][:, [0, 2, 1]]
    # drop degenerate slivers (three nearly collinear boundary nodes), relative to the local facet size
    keep = np.abs(signed) > 1e-9 * H * H
    F = F[keep]
    inner = np.all(F < n_inner_nodes, axis=1)
    F = np.concatenate([F[inner], F[~inner]])
    n_inner = int(inner.sum())

    say("placing vertices on the Moon")
    meta0 = {"center_lat_deg": lat, "center_lon_deg": lon, "reference_radius_m": Rref}
    V = geographic_to_local(lat_n, lon_n, heights, meta0)
    meta = {
        "kind": "dem",
        "dem_source": info.name,
        "dem_path": str(info.path),
        "crs_wkt": info.crs_wkt,
        "crs_name": crs.name,
        **meta0,
        "radius_km": R / 1e3,
        "resolution_m": H,
        "outer_radius_km": None if R2 is None else R2 / 1e3,
        "outer_resolution_m": H2,
        "height_kind": kind,
        "height_scale": info.scale * info.unit_factor,
        "height_offset": info.offset * info.unit_factor,
        "dem_pixel_m": info.pixel_m,
        "dem_ground_pixel_m": plan["ground_pixel_m"],
        "dem_overrides": dict(info.overrides),
        "n_facets": int(len(F)),
        "n_inner": n_inner,
        "n_vertices": int(len(V)),
        "frame": "ENU at the centre, origin on the reference sphere; true 3-D positions; inner facets first",
    }
    if kind == "tangent":
        meta["tangent_origin_lat_deg"] = info.origin_lat_deg
        meta["tangent_origin_lon_deg"] = info.origin_lon_deg
    say(f"{len(F)} facets ({n_inner} inner)")
    return Mesh(V, F, meta)


# ------------------------------------------------------------------------- reading heights (tests)


def read_heights(
    path,
    height_kind: str = "auto",
    crs: Optional[str] = None,
    xy_units: Optional[str] = None,
    z_units: Optional[str] = None,
) -> tuple[np.ndarray, DEMInfo, str]:
    """The whole raster as heights above the reference sphere [m] (NaN at nodata); for small files.

    ``height_kind`` and the overrides ``crs``, ``xy_units``, ``z_units`` as in :func:`site_mesh`.
    Returns (heights (rows, cols) [m], info, the height kind used).
    """
    rasterio, _ = _libs()
    if height_kind not in HEIGHT_KINDS:
        raise ConfigError(f"height_kind = {height_kind!r} must be one of {', '.join(HEIGHT_KINDS)}")
    info = open_dem(path, crs=crs, xy_units=xy_units, z_units=z_units)
    if info.width * info.height > 50_000_000:
        raise DEMError(f"DEM {info.name!r} is too large to read whole ({info.width} x {info.height}); mesh a site")
    with rasterio.open(info.path) as src:
        raw = src.read(1, masked=True).astype(np.float64).filled(np.nan)
    v = (raw * info.scale + info.offset) * info.unit_factor
    kind = height_kind
    if kind == "auto":
        kind = "radius" if float(np.nanmedian(v)) > 0.5 * info.reference_radius_m else "height"
    if kind == "radius":
        return v - info.reference_radius_m, info, kind
    if kind == "tangent":
        _, pyproj = _libs()
        pcrs = pyproj.CRS.from_wkt(info.crs_wkt)
        tr = rasterio.Affine(*info.transform)
        cols, rows = np.meshgrid(np.arange(info.width) + 0.5, np.arange(info.height) + 0.5)
        x = tr.a * cols + tr.b * rows + tr.c
        y = tr.d * cols + tr.e * rows + tr.f
        lon, lat = _transformer(pcrs, pcrs.geodetic_crs).transform(x, y)
        return _tangent_to_height(v, np.asarray(lat), np.asarray(lon), info), info, kind
    return v, info, kind


# ------------------------------------------------------------------------- synthetic polar sites


def _fractal(ny: int, nx: int, pixel_m: float, rms_m: float, hurst: float, rng) -> np.ndarray:
    """Self-affine random surface (power spectrum ~ k**-(2 hurst + 2)), zero mean, RMS ``rms_m`` [m]."""
    if rms_m <= 0.0:
        return np.zeros((ny, nx))
    ky = np.fft.fftfreq(ny, d=pixel_m)
    kx = np.fft.rfftfreq(nx, d=pixel_m)
    k = np.hypot(ky[:, None], kx[None, :])
    k[0, 0] = np.inf
    amp = k ** (-(hurst + 1.0))
    spec = amp * (rng.standard_normal(k.shape) + 1j * rng.standard_normal(k.shape))
    z = np.fft.irfft2(spec, s=(ny, nx))
    z -= z.mean()
    return z * (rms_m / max(float(z.std()), 1e-300))


def _crater_relief(diameter_km: float, r: np.ndarray) -> np.ndarray:
    """Height of the idealized crater (geometry's Table 7.1 profile) at ground distance r [m] from its centre."""
    from crater_thermal.geometry import crater_profile

    pieces, meta = crater_profile(diameter_km)
    prof = np.concatenate([pc.point(np.linspace(0.0, 1.0, 400)) for pc in pieces])
    order = np.argsort(prof[:, 0], kind="stable")
    return np.interp(r, prof[order, 0], prof[order, 1], right=0.0)


def synthetic_heights(
    lat_deg: float,
    lon_deg: float,
    size_km: float,
    pixel_m: float,
    craters: Sequence[tuple] = (),
    roughness_m: float = 0.0,
    hurst: float = 0.9,
    seed: int = 0,
) -> tuple[np.ndarray, tuple, str]:
    """A synthetic polar site: rough terrain with idealized craters, in lunar polar stereographic.

    Parameters
    ----------
    lat_deg, lon_deg : float [deg]
        Centre of the raster (planetocentric, east longitude); |lat| >= 60 deg.
    size_km : float [km]
        Side of the square raster.
    pixel_m : float [m]
        Pixel size (map units of the polar stereographic CRS, true at the pole).
    craters : sequence of (diameter_km, x_km, y_km)
        Idealized craters (thesis Table 7.1 profile, D <= 15 km) centred at offsets (x, y) [km] from the
        raster centre in the map's projected coordinates. A crater may reach beyond the raster's edge
        (only its part on the raster is drawn), but its centre must lie on the raster (|x|, |y| <= half
        the raster's side) and its rim crest must cross the raster (a raster lying wholly inside the rim
        would show only floor and wall): otherwise :class:`ConfigError`, naming the crater and the
        raster's extent.
    roughness_m : float [m]
        RMS height of a self-affine background (Hurst exponent ``hurst``; lunar terrain ~0.9).
    seed : int
        Random seed of the background.

    Returns
    -------
    heights : (rows, cols) float32 [m] above the reference sphere (row 0 = top = largest y)
    transform : affine tuple (a, b, c, d, e, f)
    crs_wkt : str  IAU_2015:30135 (south) or 30130 (north)
    """
    lat = _number("lat_deg", lat_deg, -90.0, 90.0)
    lon = _number("lon_deg", lon_deg, -360.0, 360.0)
    if abs(lat) < 60.0:
        raise ConfigError(f"lat_deg = {lat_deg!r}: synthetic sites are polar, |lat| >= 60 deg")
    size = _number("size_km", size_km, 1e-3, 2000.0) * 1e3
    px = _number("pixel_m", pixel_m, 0.1, 10_000.0)
    rough = _number("roughness_m", roughness_m, 0.0, 10_000.0)
    hurst = _number("hurst", hurst, 0.0, 1.0)
    n = int(round(size / px))
    if n < 4 or n * n > 64_000_000:
        raise ConfigError(f"size_km / pixel_m gives {n} x {n} pixels; allowed 4 .. 8000 per side")
    crs = polar_crs(lat)
    x_c, y_c = _transformer(crs.geodetic_crs, crs).transform(lon, lat)
    x_c, y_c = round(x_c / px) * px, round(y_c / px) * px
    x0, y0 = x_c - 0.5 * n * px, y_c + 0.5 * n * px  # upper-left corner
    xs = x0 + (np.arange(n) + 0.5) * px
    ys = y0 - (np.arange(n) + 0.5) * px
    X, Y = np.meshgrid(xs, ys)
    rng = np.random.default_rng(int(seed))
    z = _fractal(n, n, px, rough, hurst, rng)
    h_scale, k_scale = _scale_factors(crs, lat, lon)
    ground = 1.0 / math.sqrt(h_scale * k_scale)  # ground metres per map metre at the site
    half = 0.5 * n * px  # [map m] from the raster centre to its edges
    for spec in craters:
        d_km, cx, cy = (float(v) for v in (tuple(spec) + (0.0, 0.0))[:3])
        r = np.hypot(X - (x_c + cx * 1e3), Y - (y_c + cy * 1e3)) * ground
        z = z + _crater_relief(d_km, r)  # checks the diameter first
        _check_crater_on_raster(d_km, cx, cy, half, ground)
    return z.astype(np.float32), (px, 0.0, x0, 0.0, -px, y0), crs.to_wkt()


def _check_crater_on_raster(d_km: float, cx_km: float, cy_km: float, half_m: float, ground: float) -> None:
    """Refuse a crater of diameter ``d_km`` [km] at map offset (cx_km, cy_km) [km] whose centre is off a
    raster of half side ``half_m`` [map m], or whose rim crest (radius D/2 [m] on the ground, ``ground``
    ground metres per map metre) lies wholly outside it."""
    name = f"crater {d_km:g}@{cx_km:g},{cy_km:g} (D_KM@X_KM,Y_KM)"
    extent = f"the raster spans x and y from {-half_m / 1e3:g} to {half_m / 1e3:g} km about its centre"
    if not (abs(cx_km * 1e3) <= half_m and abs(cy_km * 1e3) <= half_m):
        raise ConfigError(
            f"{name}: its centre lies off the raster ({extent}); move the crater onto it or enlarge size_km (--size-km)"
        )
    rim_map_m = 0.5 * d_km * 1e3 / ground
    farthest = math.hypot(half_m + abs(cx_km) * 1e3, half_m + abs(cy_km) * 1e3)
    if farthest < rim_map_m:
        raise ConfigError(
            f"{name}: its rim (radius {0.5 * d_km:g} km) lies wholly outside the raster ({extent}), which would "
            "show only the crater's floor and wall; enlarge size_km (--size-km) or make the crater smaller"
        )


def _write_atomic(files: dict, overwrite: bool) -> list[Path]:
    from crater_thermal.io import write_bytes_atomic

    existing = [p for p in files if Path(p).exists()]
    if existing and not overwrite:
        from crater_thermal.errors import OutputExistsError

        raise OutputExistsError(f"output {str(existing[0])!r} exists; pass --overwrite to replace it")
    return [write_bytes_atomic(p, data, overwrite=True) for p, data in files.items()]


def write_geotiff(
    path, heights: np.ndarray, transform: tuple, crs_wkt: str, nodata: Optional[float] = None, overwrite: bool = False
) -> Path:
    """Write heights [m above the reference sphere] as a float32 GeoTIFF (atomically)."""
    rasterio, _ = _libs()
    from rasterio.io import MemoryFile

    z = np.asarray(heights, dtype=np.float32)
    prof = dict(
        driver="GTiff",
        width=z.shape[1],
        height=z.shape[0],
        count=1,
        dtype="float32",
        crs=rasterio.crs.CRS.from_wkt(crs_wkt),
        transform=rasterio.Affine(*transform),
        nodata=nodata,
    )
    with MemoryFile() as mem:
        with mem.open(**prof) as dst:
            dst.write(z, 1)
            dst.set_band_unit(1, "m")
        data = mem.read()
    return _write_atomic({Path(path): data}, overwrite)[0]


def write_pds3(
    path,
    heights: np.ndarray,
    transform: tuple,
    pole: str = "south",
    scaling_factor: float = 0.5,
    offset_m: float = MOON_RADIUS_M,
    nodata_dn: int = -32768,
    overwrite: bool = False,
) -> Path:
    """Write heights as a LOLA-style PDS3 product: little-endian int16 ``.IMG`` + detached ``.LBL``.

    Values are stored as in LOLA's polar LDEM products: ``radius = DN * scaling_factor + offset_m``
    (absolute radii with OFFSET = 1,737,400 m). NaN heights become ``nodata_dn``. ``transform`` must be
    a north-up polar stereographic grid with square pixels (true scale at the pole, radius 1737.4 km).

    Returns the ``.LBL`` path (open that one; the ``.IMG`` lies beside it).
    """
    p = Path(path)
    img, lbl = p.with_suffix(".IMG"), p.with_suffix(".LBL")
    z = np.asarray(heights, dtype=np.float64)
    a, b, c, d, e, f = transform
    if b != 0.0 or d != 0.0 or abs(abs(e) - a) > 1e-9 * a or e >= 0:
        raise ConfigError("write_pds3 needs a north-up grid with square pixels")
    dn = np.round((z + MOON_RADIUS_M - offset_m) / scaling_factor)
    if np.nanmax(np.abs(dn)) > 32767:
        raise ConfigError("heights do not fit int16 at this scaling_factor")
    dn = np.where(np.isfinite(dn), dn, nodata_dn).astype("<i2")
    rows, cols = dn.shape
    # PDS projection offsets: (0-based) pixel-centre coordinates of the projection origin (the pole)
    spo = -c / a - 0.5
    lpo = f / a - 0.5
    lat_c = -90.0 if pole == "south" else 90.0
    label = "\r\n".join(
        [
            "PDS_VERSION_ID = PDS3",
            "RECORD_TYPE = FIXED_LENGTH",
            f"RECORD_BYTES = {2 * cols}",
            f"FILE_RECORDS = {rows}",
            f'^IMAGE = "{img.name}"',
            'PRODUCT_ID = "CRATER_THERMAL_SYNTHETIC"',
            "OBJECT = IMAGE",
            f"  LINES = {rows}",
            f"  LINE_SAMPLES = {cols}",
            "  SAMPLE_TYPE = LSB_INTEGER",
            "  SAMPLE_BITS = 16",
            '  UNIT = "METER"',
            f"  SCALING_FACTOR = {scaling_factor!r}",
            f"  OFFSET = {offset_m!r}",
            f"  MISSING_CONSTANT = {nodata_dn}",
            "END_OBJECT = IMAGE",
            "OBJECT = IMAGE_MAP_PROJECTION",
            '  MAP_PROJECTION_TYPE = "POLAR STEREOGRAPHIC"',
            f"  A_AXIS_RADIUS = {MOON_RADIUS_M / 1e3!r} <KM>",
            f"  B_AXIS_RADIUS = {MOON_RADIUS_M / 1e3!r} <KM>",
            f"  C_AXIS_RADIUS = {MOON_RADIUS_M / 1e3!r} <KM>",
            '  POSITIVE_LONGITUDE_DIRECTION = "EAST"',
            f"  CENTER_LATITUDE = {lat_c!r} <DEG>",
            "  CENTER_LONGITUDE = 0.0 <DEG>",
            f"  MAP_SCALE = {a / 1e3!r} <KM/PIXEL>",
            f"  LINE_PROJECTION_OFFSET = {lpo!r}",
            f"  SAMPLE_PROJECTION_OFFSET = {spo!r}",
            "  MAP_PROJECTION_ROTATION = 0.0",
            "END_OBJECT = IMAGE_MAP_PROJECTION",
            "END",
            "",
        ]
    ).encode("ascii")
    _write_atomic({img: dn.tobytes(), lbl: label}, overwrite)
    return lbl


# ------------------------------------------------------------------------------------- map export


def local_crs(lat_deg: float, lon_deg: float):
    """The crater-centred map CRS of an idealized crater (pyproj CRS).

    Azimuthal equidistant, centred on (``lat_deg``, ``lon_deg``) [deg] (planetocentric, east longitude), on
    the Moon's IAU 2015 sphere (R = 1,737,400 m), metres. Its x, y are the crater frame's east and north
    coordinates [m]: distances from the centre are true geodesic distances and azimuths are true, which is
    how a flat idealized crater is laid on the Moon (at a pole, north points along ``lon_deg``, as in
    :func:`enu_basis`).
    """
    return _aeqd(polar_crs(lat_deg).geodetic_crs, float(lat_deg), float(lon_deg))


def map_frame(meta: dict, lat_deg: float, lon_deg: float) -> tuple[str, float]:
    """The CRS of a plan-view map of a mesh, as ``(crs_wkt, unit_m)``.

    A DEM site (``meta["crs_wkt"]``): its DEM's own CRS; any other mesh: :func:`local_crs` of the centre
    (``lat_deg``, ``lon_deg``) [deg]. ``unit_m`` is the size of the CRS's linear unit [m].
    """
    _, pyproj = _libs()
    if meta.get("crs_wkt"):
        crs = pyproj.CRS.from_wkt(meta["crs_wkt"])
    else:
        crs = local_crs(lat_deg, lon_deg)
    return crs.to_wkt(), _axis_metres(crs)


def to_map_xy(points, meta: dict) -> tuple[np.ndarray, np.ndarray]:
    """Mesh points [m] (site or crater frame) to the map coordinates of :func:`map_frame` [CRS units].

    A DEM site: :func:`local_to_dem_xy`; any other mesh: the frame's east and north coordinates, which
    are the :func:`local_crs` coordinates [m].
    """
    pts = np.asarray(points, float)
    if meta.get("crs_wkt"):
        x, y = local_to_dem_xy(pts, meta)
        return np.asarray(x, float), np.asarray(y, float)
    return pts[..., 0].copy(), pts[..., 1].copy()


def write_map_geotiff(
    path, grid: np.ndarray, transform: tuple, crs_wkt: str, units: str, description: str, tags: dict
) -> Path:
    """Write one map band as a float32 GeoTIFF (nodata NaN) at ``path`` (not atomically: give it the
    temporary of :func:`crater_thermal.io.atomic_output`).

    Parameters
    ----------
    grid : (ny, nx) float
        Values [``units``], NaN where there is no data; row 0 is the north (top) row.
    transform : tuple of 6 float
        Affine pixel -> map (a, b, c, d, e, f) [CRS units].
    crs_wkt : str
        The map's CRS.
    units, description : str
        The band's unit (e.g. ``"K"``) and description.
    tags : dict
        Dataset-level metadata (GDAL metadata items; values written as text).
    """
    rasterio, _ = _libs()
    z = np.asarray(grid, dtype=np.float32)
    prof = dict(
        driver="GTiff",
        width=z.shape[1],
        height=z.shape[0],
        count=1,
        dtype="float32",
        crs=rasterio.crs.CRS.from_wkt(crs_wkt),
        transform=rasterio.Affine(*transform),
        nodata=float("nan"),
        compress="deflate",
    )
    with rasterio.open(Path(path), "w", **prof) as dst:
        dst.write(z, 1)
        dst.set_band_unit(1, units)
        dst.set_band_description(1, description)
        dst.update_tags(**{str(k): str(v) for k, v in tags.items()})
        dst.update_tags(1, units=units)
    return Path(path)
