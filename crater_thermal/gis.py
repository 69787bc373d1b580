"""GIS export: a per-facet quantity of a run or a replay, reduced over time, rasterized to a GeoTIFF.

``crater-thermal export`` and :func:`crater_thermal.api.export_map` drive :func:`export_map`.

* **Quantity.** A run: one of its (time, facet) series (:data:`RUN_VARIABLES`: surface temperature [K],
  fluxes [W m-2]). A replay: ``surface_temperature`` of one profile [K] (default the nominal), or
  ``profile_minus_nominal``, that profile minus the nominal one [K] (default the loose profile, 800/1100).
* **Posterior** of an inversion (``crater-thermal invert``, needs its ``run`` for the mesh): one of
  :data:`POSTERIOR_VARIABLES` per footprint (``p_loose`` [-]: the P(loose) map of a site; MAP, mean, sd
  of the densities [kg m-3]) on the facet its samples see (the mean where several footprints share a
  facet; NaN on unobserved facets; a footprint whose samples are centred on different facets is left
  out). No statistic over time.
* **Statistic over time** (:data:`STATISTICS`): ``night_median`` (per facet, over the samples that are
  night for that facet by :func:`crater_thermal.regions.night_day_masks`, default definition; NaN where a
  facet has no night), ``mean``, ``min``, ``max``, ``at`` (the sample nearest an ISO UTC time).
* **Facets.** Only the analysed (inner) facets of a DEM site; all facets of any other mesh.
* **Raster.** The map CRS is the DEM's own for a DEM site and a crater-centred lunar azimuthal
  equidistant CRS otherwise (:func:`crater_thermal.terrain.map_frame`). Each pixel takes the value of
  the facet whose projected triangle contains the pixel centre (barycentric test, :func:`rasterize_facets`);
  pixels outside the mesh are NaN (the nodata value). The pixel size defaults to the mean projected edge
  of the exported facets [m].
* **Provenance** in the GeoTIFF's metadata: variable, statistic, units, source file, profile(s), time,
  night definition, software version.
"""

from __future__ import annotations

import inspect
import math
from pathlib import Path
from typing import Optional

import numpy as np

from crater_thermal import analysis, io, profiles, regions, terrain
from crater_thermal._version import __version__
from crater_thermal.errors import ConfigError, FluxFileError

#: The (time, facet) series of a run that can be exported.
RUN_VARIABLES = ("surface_temperature", "solar_incident", "solar_direct", "ir_incident", "solar_absorbed")
#: The quantities of a replay that can be exported.
REPLAY_VARIABLES = ("surface_temperature", "profile_minus_nominal")
#: Statistics over time.
#: Variables of an inversion's posterior (``crater-thermal invert``), one value per footprint
POSTERIOR_VARIABLES = (
    "p_loose",
    "map_top_kg_m3",
    "map_bottom_kg_m3",
    "mean_top_kg_m3",
    "mean_bottom_kg_m3",
    "sd_top_kg_m3",
    "sd_bottom_kg_m3",
)
STATISTICS = ("night_median", "mean", "min", "max", "at")
#: Largest raster written [pixels] (4 bytes each): a finer ``pixel_m`` is refused.
MAX_PIXELS = 100_000_000
#: Relative tolerance of the point-in-triangle test [-]: a pixel centre on a shared edge belongs to a facet.
_EDGE_TOLERANCE = 1e-9


# ----------------------------------------------------------------------------------- statistics


def facet_statistic(values, statistic: str, night=None, index: Optional[int] = None) -> np.ndarray:
    """Reduce a (time, facet) series over time, per facet.

    Parameters
    ----------
    values : (nt, nf) float [any unit]
    statistic : str
        One of :data:`STATISTICS`.
    night : (nt, nf) bool, optional
        Night samples per facet (``night_median``).
    index : int, optional
        Sample index (``at``).

    Returns
    -------
    (nf,) float [unit of ``values``]
        NaN for a facet without night samples (``night_median``).
    """
    v = np.asarray(values, dtype=float)
    if statistic == "night_median":
        return analysis.facet_median_map(v, night)
    if statistic == "mean":
        return v.mean(axis=0)
    if statistic == "min":
        return v.min(axis=0)
    if statistic == "max":
        return v.max(axis=0)
    if statistic == "at":
        return v[int(index)].copy()
    raise ConfigError(f"statistic {statistic!r} not one of {', '.join(STATISTICS)}")


def nearest_sample(times, time: str) -> int:
    """Index of the sample nearest ``time`` (ISO UTC, e.g. ``2019-01-05T12:00``; a trailing Z is allowed).

    Raises
    ------
    ConfigError
        ``time`` is not ISO, or lies more than one sample step outside the record.
    """
    t_all = np.asarray(times).astype("datetime64[ns]")
    try:
        t = np.datetime64(str(time).strip().rstrip("Zz"), "ns")
    except ValueError:
        raise ConfigError(f"time = {time!r} is not an ISO UTC date-time (e.g. 2019-01-05T12:00)") from None
    step = (t_all[1] - t_all[0]) if t_all.size > 1 else np.timedelta64(0, "ns")
    if np.isnat(t) or t < t_all[0] - step or t > t_all[-1] + step:
        first, last = (np.datetime_as_string(x, unit="m") for x in (t_all[0], t_all[-1]))
        raise ConfigError(f"time = {time!r} is outside the record [{first}, {last}] UTC")
    return int(np.argmin(np.abs((t_all - t).astype(np.int64))))


def _night_defaults() -> dict:
    """regions.night_day_masks' own defaults (definition, min_dark_hours, ...), so that tags name them."""
    sig = inspect.signature(regions.night_day_masks)
    return {k: p.default for k, p in sig.parameters.items() if p.default is not inspect.Parameter.empty}


# -------------------------------------------------------------------------------- rasterization


def raster_grid(x, y, pixel: float) -> tuple[tuple, int, int]:
    """A north-up grid covering points, aligned on multiples of ``pixel``.

    Parameters
    ----------
    x, y : (n,) float [map units]
    pixel : float [map units]

    Returns
    -------
    transform : tuple of 6 float
        Affine pixel -> map (a, b, c, d, e, f).
    nx, ny : int
        Columns and rows.
    """
    x0 = math.floor(float(np.min(x)) / pixel) * pixel
    y1 = math.ceil(float(np.max(y)) / pixel) * pixel
    nx = max(1, math.ceil((float(np.max(x)) - x0) / pixel))
    ny = max(1, math.ceil((y1 - float(np.min(y))) / pixel))
    return (pixel, 0.0, x0, 0.0, -pixel, y1), nx, ny


def rasterize_facets(xy, faces, values, transform: tuple, nx: int, ny: int, chunk: int = 200_000) -> np.ndarray:
    """Each pixel the value of the triangle that contains its centre (barycentric test, vectorized).

    Parameters
    ----------
    xy : (nv, 2) float [map units]
        Projected vertices.
    faces : (nf, 3) int
        Triangles to draw (indices into ``xy``).
    values : (nf,) float
        One value per triangle.
    transform : tuple of 6 float
        North-up affine pixel -> map (a, 0, c, 0, e, f) with e < 0, as :func:`raster_grid`.
    nx, ny : int
        Raster size [pixels].
    chunk : int
        Candidate (triangle, pixel) pairs tested at once (bounds memory).

    Returns
    -------
    (ny, nx) float64
        NaN where no triangle contains the pixel centre. A centre on an edge shared by two triangles
        takes the later one.
    """
    a, _, c, _, e, f = transform
    out = np.full((ny, nx), np.nan)
    tri = np.asarray(xy, float)[np.asarray(faces, np.int64)]  # (nf, 3, 2)
    vals = np.asarray(values, float)
    # pixel-centre column i has x = c + (i + 0.5) a; row j has y = f + (j + 0.5) e
    col_lo = np.clip(np.ceil((tri[:, :, 0].min(1) - c) / a - 0.5), 0, nx).astype(np.int64)
    col_hi = np.clip(np.floor((tri[:, :, 0].max(1) - c) / a - 0.5), -1, nx - 1).astype(np.int64)
    row_lo = np.clip(np.ceil((tri[:, :, 1].max(1) - f) / e - 0.5), 0, ny).astype(np.int64)
    row_hi = np.clip(np.floor((tri[:, :, 1].min(1) - f) / e - 0.5), -1, ny - 1).astype(np.int64)
    ncol = np.maximum(col_hi - col_lo + 1, 0)
    nrow = np.maximum(row_hi - row_lo + 1, 0)
    count = ncol * nrow
    ends = np.cumsum(count)
    start = 0
    while start < len(count):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + chunk, side="right"))
        stop = max(stop, start + 1)
        idx = np.arange(start, stop)
        n = count[idx]
        t = np.repeat(idx, n)
        if t.size:
            k = np.arange(t.size) - np.repeat(np.cumsum(n) - n, n)  # position within the triangle's box
            col = col_lo[t] + k % ncol[t]
            row = row_lo[t] + k // ncol[t]
            px = c + (col + 0.5) * a
            py = f + (row + 0.5) * e
            p0, p1, p2 = tri[t, 0], tri[t, 1], tri[t, 2]
            d = (p1[:, 1] - p2[:, 1]) * (p0[:, 0] - p2[:, 0]) + (p2[:, 0] - p1[:, 0]) * (p0[:, 1] - p2[:, 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                l0 = ((p1[:, 1] - p2[:, 1]) * (px - p2[:, 0]) + (p2[:, 0] - p1[:, 0]) * (py - p2[:, 1])) / d
                l1 = ((p2[:, 1] - p0[:, 1]) * (px - p2[:, 0]) + (p0[:, 0] - p2[:, 0]) * (py - p2[:, 1])) / d
            l2 = 1.0 - l0 - l1
            inside = (d != 0) & (l0 >= -_EDGE_TOLERANCE) & (l1 >= -_EDGE_TOLERANCE) & (l2 >= -_EDGE_TOLERANCE)
            out[row[inside], col[inside]] = vals[t[inside]]
        start = stop
    return out


# ------------------------------------------------------------------------------------ quantities


def _open(path: Path):
    """A run (loaded lazily) or a replay, told apart by its ``profile`` dimension; (dataset, kind)."""
    probe = io.open_written(path)
    if "footprint" in probe.dims and "p_loose" in probe:
        return probe, "posterior"
    is_replay = "profile" in probe.dims
    probe.close()
    return (io.open_replay(path), "replay") if is_replay else (io.open_run(path, load=False), "run")


def _posterior_per_facet(post, variable: str, run) -> tuple[np.ndarray, str, dict]:
    """(per-facet values, units, tags) of a posterior's per-footprint ``variable`` (NaN where unobserved)."""
    if variable not in POSTERIOR_VARIABLES:
        raise ConfigError(
            f"variable = {variable!r} is not a posterior variable; allowed: {', '.join(POSTERIOR_VARIABLES)}"
        )
    h_post, h_run = post.attrs.get("mesh_hash"), run.attrs.get("mesh_hash")
    if h_post is not None and h_run is not None and str(h_post) != str(h_run):
        raise ConfigError("the posterior was not made from this run (mesh_hash differs); give its run with --run")
    if "facet" not in post:
        raise ConfigError("the posterior has no footprint facets (made by an older version); invert again")
    facet = np.asarray(post["facet"].values, np.int64)
    nf = int(run.sizes["facet"])
    if np.any(facet >= nf):
        raise ConfigError(f"the posterior's facets exceed the run's {nf}; give its run with --run")
    if np.all(facet < 0):
        raise ConfigError("no footprint of the posterior is centred on one facet: nothing to map")
    values = np.asarray(post[variable].values, float)
    per_facet = np.full(nf, np.nan)
    seen = facet >= 0
    # several footprints on one facet: their mean
    total = np.bincount(facet[seen], weights=values[seen], minlength=nf)
    count = np.bincount(facet[seen], minlength=nf)
    per_facet[count > 0] = total[count > 0] / count[count > 0]
    units = str(post[variable].attrs.get("units", ""))
    tags = {"threshold_bottom_kg_m3": post.attrs.get("loose_bottom_kg_m3", "")} if variable == "p_loose" else {}
    tags["footprints_mapped"] = f"{int(seen.sum())} of {facet.size} (footprints centred on several facets left out)"
    return per_facet, units, tags


def _profile_label(replay, profile: Optional[str], default: Optional[str]) -> str:
    """The replay's label of ``profile`` (a label, or TOP/BOTTOM [kg m-3] matched by densities)."""
    labels = analysis.profile_labels(replay)
    if profile is None:
        if default is None:
            raise ConfigError(f"give --profile: one of {', '.join(labels)}")
        return default
    if profile in labels:
        return profile
    top_bottom = profiles.parse_two_layer(str(profile))
    found = analysis.find_profile(replay, *top_bottom) if top_bottom else None
    if found is None:
        raise ConfigError(f"profile = {profile!r} is not in the replay; allowed: {', '.join(labels)}")
    return found


def _quantity(ds, kind: str, variable: str, profile: Optional[str], run) -> tuple[np.ndarray, str, dict]:
    """(values (nt, nf), units, provenance tags) of the quantity to export."""
    if kind == "run":
        if variable not in RUN_VARIABLES:
            raise ConfigError(f"variable = {variable!r} is not a run variable; allowed: {', '.join(RUN_VARIABLES)}")
        if profile is not None:
            raise ConfigError("--profile applies to a replay; this is a run")
        if variable not in ds:
            raise FluxFileError(f"the run has no variable {variable!r}")
        return np.asarray(ds[variable].values, float), str(ds[variable].attrs.get("units", "")), {}
    if variable not in REPLAY_VARIABLES:
        raise ConfigError(
            f"variable = {variable!r} is not a replay quantity; allowed: {', '.join(REPLAY_VARIABLES)} "
            "(export a run for its fluxes)"
        )
    labels = analysis.profile_labels(ds)
    nominal = analysis.nominal_label(ds, ds)
    if variable == "surface_temperature":
        lab = _profile_label(ds, profile, nominal if nominal in labels else labels[0])
        return analysis.profile_temperature(ds, lab), "K", {"profile": lab}
    lab = _profile_label(ds, profile, analysis.loose_label(ds, nominal))
    if lab == nominal:
        raise ConfigError(f"profile = {lab!r} is the nominal profile: its difference to the nominal is zero")
    if nominal in labels:
        nom = analysis.profile_temperature(ds, nominal)
        nominal_source = "replay"
    elif run is not None:
        nom = np.asarray(run["surface_temperature"].values, float)
        nominal_source = "run"
    else:
        raise ConfigError(
            f"the replay has no nominal profile {nominal!r}: give its run (--run RUN.nc) for the nominal temperature"
        )
    tags = {"profile": lab, "nominal_profile": nominal, "nominal_from": nominal_source}
    return analysis.profile_temperature(ds, lab) - nom, "K", tags


# ---------------------------------------------------------------------------------------- driver


def export_map(
    source,
    output,
    variable: str = "surface_temperature",
    statistic: str = "night_median",
    *,
    time: Optional[str] = None,
    profile: Optional[str] = None,
    run=None,
    pixel_m: Optional[float] = None,
    night: Optional[str] = None,
    overwrite: bool = False,
) -> Path:
    """Rasterize a per-facet statistic of a run or replay to a GeoTIFF (see the module docstring).

    Parameters
    ----------
    source : path-like
        A run, a replay or an inversion's posterior (netCDF; a posterior needs ``run``).
    output : path-like
        The GeoTIFF to write (``.tif`` or ``.tiff``); never one of the inputs.
    variable : str
        :data:`RUN_VARIABLES` for a run, :data:`REPLAY_VARIABLES` for a replay, :data:`POSTERIOR_VARIABLES`
        for a posterior.
    statistic : str
        One of :data:`STATISTICS`; ``"at TIME"`` is the same as ``statistic="at", time=TIME``.
    time : str, optional
        ISO UTC time for ``at`` (the nearest sample).
    profile : str, optional
        A replay's profile: a label or TOP/BOTTOM [kg m-3] (default: the nominal for
        ``surface_temperature``, the loose 800/1100 for ``profile_minus_nominal``).
    run : path-like, optional
        The run a replay or posterior was made from: needed for ``night_median`` of a replay (the per-facet
        night uses the run's direct sunlight), when the replay lacks the nominal profile, and for a
        posterior (its mesh).
    pixel_m : float, optional
        Pixel size [m], > 0; default the mean projected edge of the exported facets.
    night : str, optional
        Night definition (:data:`crater_thermal.regions.NIGHT_DEFINITIONS`); default that of
        :func:`crater_thermal.regions.night_day_masks`.
    overwrite : bool
        Replace an existing ``output``.

    Returns
    -------
    Path
        ``output``.

    Raises
    ------
    ConfigError
        Unknown variable, statistic, profile or night definition; a bad time; a bad ``pixel_m`` or a
        raster over :data:`MAX_PIXELS`; an output that is an input or not ``.tif``.
    FluxFileError, OutputExistsError
        As :func:`crater_thermal.io.open_run` / :func:`crater_thermal.io.check_output`.
    """
    source = Path(source)
    output = Path(output)
    statistic = str(statistic).strip()
    if statistic.startswith("at ") and time is None:
        statistic, time = "at", statistic[3:].strip()
    if statistic not in STATISTICS:
        raise ConfigError(f"statistic = {statistic!r} is not one of {', '.join(STATISTICS)} (at needs --time)")
    if statistic == "at" and not time:
        raise ConfigError("statistic 'at' needs a time (--time 2019-01-05T12:00, ISO UTC)")
    if statistic != "at" and time is not None:
        raise ConfigError(f"--time applies to statistic 'at', not {statistic!r}")
    if output.suffix.lower() not in (".tif", ".tiff"):
        raise ConfigError(f"output {output} must be a GeoTIFF (.tif or .tiff)")
    if pixel_m is not None and not (math.isfinite(float(pixel_m)) and float(pixel_m) > 0):
        raise ConfigError(f"pixel_m = {pixel_m!r} must be a positive number of metres")
    inputs = [source] + ([Path(run)] if run is not None else [])
    io.check_output(output, overwrite, inputs=inputs)
    ds, kind = _open(source)
    run_ds = None
    try:
        if kind == "posterior":
            if run is None:
                ds.close()
                raise ConfigError("a posterior map needs its run (--run RUN.nc): the mesh")
            run_ds = io.open_run(run, load=False)
            per_facet, units, tags = _posterior_per_facet(ds, variable, run_ds)
            statistic = "per footprint"
            ds.close()
            ds = run_ds
            run_ds = None
        elif run is not None:
            if kind != "run":
                run_ds = io.open_run(run, load=False)
                io.check_pair(run_ds, ds)
            else:
                raise ConfigError("--run applies to a replay; this is a run")
        if kind != "posterior":
            values, units, tags = _quantity(ds, kind, variable, profile, run_ds)
        night_mask = None
        if kind == "posterior":
            pass
        elif statistic == "night_median":
            defaults = _night_defaults()
            definition = night if night is not None else defaults.get("definition")
            night_src = ds if kind == "run" else run_ds
            if night_src is None:
                raise ConfigError(
                    "night_median of a replay needs its run (--run RUN.nc): the per-facet night uses the run's "
                    "direct sunlight"
                )
            night_mask, _ = regions.night_day_masks(night_src, definition=definition)
            tags["night_definition"] = definition
            if "min_dark_hours" in defaults:
                tags["night_min_dark_hours"] = defaults["min_dark_hours"]
        index = None
        if statistic == "at":
            index = nearest_sample(ds["time"].values, time)
            tags["time_utc"] = np.datetime_as_string(np.asarray(ds["time"].values)[index], unit="s") + "Z"
        if kind != "posterior":
            per_facet = facet_statistic(values, statistic, night_mask, index)
        inner = io.dataset_inner(ds)
        meta = io.mesh_meta(ds)
        lat, lon = io.latitude_deg(ds), float(ds.attrs.get("lon_deg", meta.get("center_lon_deg", 0.0)))
        vertices = np.asarray(ds["mesh_vertices"].values, float)
        faces = np.asarray(ds["mesh_faces"].values, np.int64)
    finally:
        ds.close()
        if run_ds is not None:
            run_ds.close()
    crs_wkt, unit_m = terrain.map_frame(meta, lat, lon)
    x, y = terrain.to_map_xy(vertices, meta)
    xy = np.stack([x, y], axis=1)
    faces = faces[inner]
    used = xy[np.unique(faces)]
    if pixel_m is None:
        edges = xy[faces] - xy[np.roll(faces, -1, axis=1)]
        pixel_m = float(np.mean(np.hypot(edges[..., 0], edges[..., 1]))) * unit_m
    pixel = float(pixel_m) / unit_m
    transform, nx, ny = raster_grid(used[:, 0], used[:, 1], pixel)
    if nx * ny > MAX_PIXELS:
        raise ConfigError(
            f"pixel_m = {pixel_m:g} m gives a raster of {nx} x {ny} pixels, over {MAX_PIXELS:,}: "
            "choose a larger --pixel-m"
        )
    grid = rasterize_facets(xy, faces, per_facet[inner], transform, nx, ny)
    tags.update(
        {
            "variable": variable,
            "statistic": statistic,
            "units": units,
            "source": str(source.resolve()),
            "source_kind": kind,
            "facets": f"{int(inner.sum())} of {inner.size} ({'analysed inner facets' if not inner.all() else 'all'})",
            "pixel_m": f"{pixel_m:.6g}",
            "crs_kind": "DEM CRS" if meta.get("crs_wkt") else "crater-centred azimuthal equidistant, Moon sphere",
            "lat_deg": lat,
            "lon_deg": lon,
            "rasterization": "pixel centre in the facet's projected triangle; NaN outside the mesh",
            "software": f"crater_thermal {__version__}",
        }
    )
    if run is not None:
        tags["run"] = str(Path(run).resolve())
    description = f"{variable} {statistic} [{units}]"
    with io.atomic_output(output, overwrite) as tmp:
        terrain.write_map_geotiff(tmp, grid, transform, crs_wkt, units, description, tags)
    return output
