"""Datasets on disk: the flux / run / replay / steady schemas, validation, atomic writes, checkpoints.

This is the only module that imports xarray. Files are netCDF4 with CF-style ``units``
attributes. The schemas are contracts (see ``ARCHITECTURE.md``):

Flux dataset (the minimum ``replay`` accepts)
    ``time`` (datetime64, UTC, strictly increasing), ``solar_incident(time, facet)`` and
    ``ir_incident(time, facet)`` [W m-2]; global attributes ``albedo`` and ``emissivity``.
    Between samples the fluxes are linear in time.
Run dataset
    The flux variables plus ``solar_direct``, ``surface_temperature(time, facet)`` [K],
    ``sun_direction(time, xyz)`` (crater frame, unit), ``sun_distance(time)`` [au], the mesh
    (``mesh_vertices(vertex, xyz)`` [m], ``mesh_faces(facet, corner)``, ``area`` [m2],
    ``normal``, ``centroid`` [m]) and attributes (case TOML text, version, mesh hash, ...).
Replay dataset
    ``surface_temperature(profile, time, facet)`` [K] with coordinates ``profile`` (labels),
    ``rho_top(profile)``, ``rho_bottom(profile)`` [kg m-3], plus the run's mesh and attributes.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import xarray as xr

from crater_thermal import __version__
from crater_thermal.errors import FluxFileError, OutputExistsError

#: Accepted spellings of the irradiance unit.
FLUX_UNITS = ("W m-2", "W m**-2", "W m^-2", "W/m2", "W/m^2", "W m-2 ")
#: Accepted spellings of the temperature unit.
TEMPERATURE_UNITS = ("K", "kelvin")
#: Compression for large float variables (lossless).
_ENCODING = {"zlib": True, "complevel": 1}


# ----------------------------------------------------------------------------- writing


def check_output(path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Refuse an existing output unless ``overwrite``; create the parent folder.

    Returns the output path. Raises :class:`OutputExistsError`.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(f"output {path} exists; pass --overwrite to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def write_dataset_atomic(ds: xr.Dataset, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write ``ds`` to netCDF4 at ``path`` atomically (temporary file in the same folder, then rename).

    An interrupted write never leaves a half-written file at ``path`` nor damages an earlier one.
    """
    path = check_output(path, overwrite)
    encoding = {
        name: dict(_ENCODING)
        for name, var in ds.data_vars.items()
        if var.dtype.kind == "f" and var.size > 1000
    }
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4", encoding=encoding)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; results are ordinary files
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def write_bytes_atomic(path: str | os.PathLike, data: bytes, overwrite: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then rename; umask permissions).

    Raises :class:`OutputExistsError` if ``path`` exists and ``overwrite`` is False.
    """
    path = check_output(path, overwrite)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_npz_atomic(path: str | os.PathLike, **arrays: Any) -> Path:
    """Save arrays to an ``.npz`` file atomically (used for checkpoints and caches)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.npz", dir=path.parent)
    os.close(fd)
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def mesh_variables(mesh) -> dict:
    """The mesh as dataset variables: vertices [m], faces, area [m2], unit normals, centroids [m]."""
    return {
        "mesh_vertices": (("vertex", "xyz"), np.asarray(mesh.vertices, float), {"units": "m"}),
        "mesh_faces": (("facet", "corner"), np.asarray(mesh.faces, np.int64), {}),
        "area": (("facet",), np.asarray(mesh.areas, float), {"units": "m2"}),
        "normal": (("facet", "xyz"), np.asarray(mesh.normals, float), {"units": "1"}),
        "centroid": (("facet", "xyz"), np.asarray(mesh.centroids, float), {"units": "m"}),
        "inner": (("facet",), inner_flags(len(mesh.faces), getattr(mesh, "meta", None)).astype(np.int8),
                  {"units": "1", "flag_values": np.array([0, 1], np.int8), "flag_meanings": "outer inner",
                   "long_name": "facet of the analysed region (0: outer terrain for shadows and radiation only)"}),
    }


def inner_flags(n_facets: int, meta: Mapping[str, Any] | None) -> np.ndarray:
    """(n_facets,) bool: facets of the analysed region. A DEM site mesh stores its inner facets first and
    their count as ``meta["n_inner"]``; every other mesh is all inner."""
    mask = np.ones(int(n_facets), dtype=bool)
    n_inner = (meta or {}).get("n_inner")
    if n_inner is not None:
        mask[int(n_inner):] = False
    return mask


def dataset_inner(ds: xr.Dataset) -> np.ndarray:
    """(n_facets,) bool ``inner`` flags of a run/replay dataset (all True for files written before the flag)."""
    if "inner" in ds:
        return np.asarray(ds["inner"].values).astype(bool)
    return np.ones(ds.sizes["facet"], dtype=bool)


def base_attrs(mesh, **attrs: Any) -> dict:
    """Global attributes every dataset carries (version, mesh hash, mesh meta as JSON)."""
    out = {
        "software": "crater_thermal",
        "software_version": __version__,
        "mesh_hash": mesh.hash,
        "mesh_meta": json.dumps(mesh.meta, default=float),
        "Conventions": "CF-1.8",
    }
    for key, value in attrs.items():
        if value is None:
            continue
        if isinstance(value, bool):
            value = int(value)
        elif isinstance(value, (dict, list, tuple)):
            value = json.dumps(value, default=float)
        out[key] = value
    return out


def write_steady(path, mesh, results: Mapping[str, np.ndarray], attrs: Mapping[str, Any],
                 overwrite: bool = False) -> Path:
    """Write a steady-state (radiative equilibrium) result.

    Parameters
    ----------
    results : mapping with ``surface_temperature`` [K] and ``solar_direct``, ``solar_incident``,
        ``ir_incident`` [W m-2], each ``(n_facets,)``.
    attrs : global attributes (albedo, emissivity, sun elevation/azimuth, ...).
    """
    units = {"surface_temperature": "K"}
    data_vars = {
        name: (("facet",), np.asarray(value, float), {"units": units.get(name, "W m-2")})
        for name, value in results.items()
    }
    data_vars.update(mesh_variables(mesh))
    ds = xr.Dataset(data_vars, attrs=base_attrs(mesh, **attrs))
    return write_dataset_atomic(ds, path, overwrite)


def run_dataset(mesh, times, *, solar_incident, ir_incident, solar_direct, surface_temperature,
                sun_direction, sun_distance_au, attrs: Mapping[str, Any], extra: Mapping | None = None
                ) -> xr.Dataset:
    """Assemble the run dataset (contract schema). Arrays are ``(n_times, n_facets)`` unless noted.

    ``extra`` adds variables as ``name: (dims, data, attrs)``.
    """
    flux = {"units": "W m-2"}
    data_vars = {
        "solar_incident": (("time", "facet"), solar_incident, dict(flux, long_name="direct + scattered shortwave irradiance")),
        "ir_incident": (("time", "facet"), ir_incident, dict(flux, long_name="longwave irradiance from the terrain")),
        "solar_direct": (("time", "facet"), solar_direct, dict(flux, long_name="direct solar irradiance")),
        "surface_temperature": (("time", "facet"), surface_temperature, {"units": "K"}),
        "sun_direction": (("time", "xyz"), sun_direction, {"units": "1", "frame": "crater ENU (x east, y north, z up)"}),
        "sun_distance": (("time",), sun_distance_au, {"units": "au"}),
    }
    data_vars.update(mesh_variables(mesh))
    if extra:
        data_vars.update(extra)
    ds = xr.Dataset(data_vars, coords={"time": np.asarray(times, "datetime64[ns]")},
                    attrs=base_attrs(mesh, **attrs))
    ds.attrs["flux_interpolation"] = "linear in time between samples"
    return ds


def replay_dataset(run: xr.Dataset, labels, rho_top, rho_bottom, surface_temperature,
                   attrs: Mapping[str, Any] | None = None) -> xr.Dataset:
    """Assemble the replay dataset: ``surface_temperature(profile, time, facet)`` [K] plus the run's mesh."""
    data_vars = {
        "surface_temperature": (("profile", "time", "facet"), surface_temperature, {"units": "K"}),
        "rho_top": (("profile",), np.asarray(rho_top, float), {"units": "kg m-3"}),
        "rho_bottom": (("profile",), np.asarray(rho_bottom, float), {"units": "kg m-3"}),
    }
    for name in ("mesh_vertices", "mesh_faces", "area", "normal", "centroid", "inner", "sun_direction",
                 "sun_distance"):
        if name in run:
            data_vars[name] = run[name].variable
    out_attrs = dict(run.attrs)
    out_attrs.update({k: v for k, v in (attrs or {}).items() if v is not None})
    out_attrs["software_version"] = __version__
    return xr.Dataset(data_vars, coords={"profile": np.asarray(list(labels), dtype=str), "time": run["time"].values},
                      attrs=out_attrs)


# ----------------------------------------------------------------------------- reading


def _open(path, what: str, load: bool = True) -> xr.Dataset:
    path = Path(path)
    if not path.is_file():
        raise FluxFileError(f"{what} file {path} does not exist")
    try:
        ds = xr.open_dataset(path, engine="netcdf4")
        return ds.load() if load else ds
    except Exception as exc:  # netCDF4/HDF5 raise many types for a corrupt file
        raise FluxFileError(f"cannot read {what} file {path}: {type(exc).__name__}: {exc}") from None


def _check_var(ds, path, name, dims, units) -> None:
    if name not in ds:
        raise FluxFileError(f"{path}: missing variable '{name}'")
    var = ds[name]
    if tuple(var.dims) != tuple(dims):
        raise FluxFileError(f"{path}: variable '{name}' has dims {tuple(var.dims)}, expected {tuple(dims)}")
    if units is not None:
        got = str(var.attrs.get("units", "")).strip()
        if got not in units:
            raise FluxFileError(f"{path}: variable '{name}' has units '{got}', expected '{units[0]}'")
    if var.dtype.kind not in "fc":
        return
    # block by block along the first dimension, so a lazily opened multi-GB variable is never whole in memory
    for i in range(var.shape[0]) if var.ndim == 3 else [slice(None)]:
        values = np.asarray(var[i].values)
        if not np.all(np.isfinite(values)):
            bad = int(np.size(values) - np.count_nonzero(np.isfinite(values)))
            raise FluxFileError(f"{path}: variable '{name}' has {bad} NaN/inf values")


def _check_time(ds, path) -> None:
    if "time" not in ds.coords and "time" not in ds:
        raise FluxFileError(f"{path}: missing coordinate 'time'")
    t = np.asarray(ds["time"].values)
    if t.dtype.kind != "M":
        raise FluxFileError(f"{path}: 'time' is not a datetime coordinate (dtype {t.dtype})")
    if t.size < 2:
        raise FluxFileError(f"{path}: 'time' needs at least 2 samples, has {t.size}")
    if np.any(np.isnat(t)):
        raise FluxFileError(f"{path}: 'time' has missing values")
    if np.any(np.diff(t) <= np.timedelta64(0, "ns")):
        i = int(np.argmax(np.diff(t) <= np.timedelta64(0, "ns")))
        raise FluxFileError(f"{path}: 'time' is not strictly increasing at index {i + 1} ({t[i + 1]})")


def _check_attr_range(ds, path, name, lo, hi, default=None) -> None:
    if name not in ds.attrs:
        if default is None:
            raise FluxFileError(f"{path}: missing global attribute '{name}'")
        ds.attrs[name] = default
        return
    try:
        value = float(ds.attrs[name])
    except (TypeError, ValueError):
        raise FluxFileError(f"{path}: attribute '{name}' = {ds.attrs[name]!r} is not a number") from None
    if not (lo <= value <= hi):
        raise FluxFileError(f"{path}: attribute '{name}' = {value} outside [{lo}, {hi}]")


def read_flux_dataset(path) -> xr.Dataset:
    """Open and validate a flux dataset (any file with ``time``, ``solar_incident``, ``ir_incident``).

    Raises :class:`FluxFileError` naming the problem: unreadable file, missing variable, wrong dims or
    units, NaN/inf, non-monotonic time, albedo/emissivity attributes out of range.
    """
    ds = _open(path, "flux")
    _check_time(ds, path)
    for name in ("solar_incident", "ir_incident"):
        _check_var(ds, path, name, ("time", "facet"), FLUX_UNITS)
    if np.any(ds["solar_incident"].values < 0) or np.any(ds["ir_incident"].values < 0):
        raise FluxFileError(f"{path}: negative irradiance in solar_incident or ir_incident")
    _check_attr_range(ds, path, "albedo", 0.0, 1.0)
    _check_attr_range(ds, path, "emissivity", 1e-6, 1.0)
    return ds


def open_run(path) -> xr.Dataset:
    """Open and validate a run dataset (flux schema + surface temperatures + mesh)."""
    ds = read_flux_dataset(path)
    _check_var(ds, path, "surface_temperature", ("time", "facet"), TEMPERATURE_UNITS)
    for name in ("mesh_vertices", "mesh_faces", "area"):
        if name not in ds:
            raise FluxFileError(f"{path}: missing variable '{name}'")
    return ds


def open_replay(path) -> xr.Dataset:
    """Open and validate a replay dataset (lazily: a density-grid replay can be GBs; read per profile)."""
    ds = _open(path, "replay", load=False)
    _check_time(ds, path)
    _check_var(ds, path, "surface_temperature", ("profile", "time", "facet"), TEMPERATURE_UNITS)
    for name in ("rho_top", "rho_bottom"):
        if name not in ds:
            raise FluxFileError(f"{path}: missing variable '{name}'")
    return ds
