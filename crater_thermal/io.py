"""Datasets on disk: the flux / run / replay / steady schemas, validation, checkpoints, and the one
atomic writer (:func:`atomic_output`) that every output of crater_thermal goes through.

This is the only module that imports xarray (inside the functions that need it, so that the writer
and the checks cost no xarray import). Files are netCDF4 with CF-style ``units``
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

import contextlib
import json
import os
import secrets
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Mapping

import numpy as np

from crater_thermal import __version__
from crater_thermal.errors import ConfigError, FluxFileError, OutputExistsError

if TYPE_CHECKING:
    import xarray as xr

#: Accepted spellings of the irradiance unit.
FLUX_UNITS = ("W m-2", "W m**-2", "W m^-2", "W/m2", "W/m^2", "W m-2 ")
#: Accepted spellings of the temperature unit.
TEMPERATURE_UNITS = ("K", "kelvin")
#: Compression for large float variables (lossless).
_ENCODING = {"zlib": True, "complevel": 1}


# ----------------------------------------------------------------------------- writing


def check_output(path: str | os.PathLike, overwrite: bool = False, folder: bool = False) -> Path:
    """Check an output path before any work (nothing is created): refuse it if it exists (unless
    ``overwrite``) or has the wrong kind.

    Parameters
    ----------
    path : path-like
        The file (or, with ``folder``, the folder) to write.
    overwrite : bool
        Allow replacing an existing output.
    folder : bool
        The output is a folder (a file output must not be a folder, and the reverse).

    Returns
    -------
    Path

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``overwrite`` is False.
    ConfigError
        ``path`` is a folder where a file is written (or the reverse), or its parent is a file.
    """
    path = Path(path)
    if path.is_dir() and not folder:
        raise ConfigError(f"output {path} is a folder; give a file name (e.g. {path / 'out.nc'})")
    if path.exists() and folder and not path.is_dir():
        raise ConfigError(f"output {path} is a file; give a folder name")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"output {path} exists; pass --overwrite to replace it")
    if path.parent.exists() and not path.parent.is_dir():
        raise ConfigError(f"output {path}: {path.parent} is a file, not a folder")
    return path


def _temporary_sibling(path: Path, folder: bool) -> Path:
    """Create an empty file (or folder) beside ``path`` with a fresh hidden name and return it.

    Created with mode 0o666 (0o777 for a folder) so that the process umask alone sets the
    permissions: one policy for every output.
    """
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp{path.suffix}"
        try:
            if folder:
                os.mkdir(tmp, 0o777)
            else:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {path}")  # pragma: no cover


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, overwrite: bool = False, folder: bool = False) -> Iterator[Path]:
    """Write an output atomically: the one writer every crater_thermal output goes through.

    Yields a temporary path in the same folder as ``path`` (an empty file, or with ``folder`` an empty
    folder; the name ends in ``path``'s suffix, so format-sniffing writers work). When the block ends
    normally the temporary is renamed onto ``path`` (``os.replace``: readers never see a half-written
    file, and an interrupted write never damages an earlier output); when it raises, the temporary is
    removed and ``path`` is untouched. Permissions follow the umask (files 0o666, folders 0o777, minus
    the umask).

    Parameters
    ----------
    path : path-like
        Final output path; its parent folders are created.
    overwrite : bool
        Replace an existing output (checked again at the rename, in case one appeared meanwhile).
    folder : bool
        The output is a folder; an existing one (with ``overwrite``) is replaced as a whole.

    Raises
    ------
    OutputExistsError, ConfigError
        As :func:`check_output`, before the block runs.

    Examples
    --------
    >>> with atomic_output("run.nc", overwrite=True) as tmp:  # doctest: +SKIP
    ...     ds.to_netcdf(tmp)
    """
    path = check_output(path, overwrite, folder)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"cannot create the folder of output {path}: {exc.strerror or exc}") from None
    tmp = _temporary_sibling(path, folder)
    try:
        yield tmp
        check_output(path, overwrite, folder)
        if folder and path.is_dir():
            old = _temporary_sibling(path, folder=True)
            os.replace(path, old)  # a folder cannot be renamed onto a non-empty one: swap
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)
                raise
            _remove(old)
        else:
            _fsync(tmp)  # the data reach the disk before the name does
            os.replace(tmp, path)
    finally:
        if os.path.lexists(tmp):
            _remove(tmp)


def write_dataset_atomic(ds: xr.Dataset, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write ``ds`` to netCDF4 at ``path`` through :func:`atomic_output`.

    An interrupted write never leaves a half-written file at ``path`` nor damages an earlier one.
    """
    encoding = {
        name: dict(_ENCODING)
        for name, var in ds.data_vars.items()
        if var.dtype.kind == "f" and var.size > 1000
    }
    with atomic_output(path, overwrite) as tmp:
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4", encoding=encoding)
    return Path(path)


def write_bytes_atomic(path: str | os.PathLike, data: bytes, overwrite: bool = False) -> Path:
    """Write ``data`` to ``path`` through :func:`atomic_output`.

    Raises :class:`OutputExistsError` if ``path`` exists and ``overwrite`` is False.
    """
    with atomic_output(path, overwrite) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def save_npz_atomic(path: str | os.PathLike, **arrays: Any) -> Path:
    """Save arrays to an ``.npz`` file through :func:`atomic_output`, replacing any earlier one
    (checkpoints and caches)."""
    with atomic_output(path, overwrite=True) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return Path(path)


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
    import xarray as xr

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
    import xarray as xr

    flux = {"units": "W m-2"}
    data_vars = {
        "solar_incident": (("time", "facet"), solar_incident,
                           dict(flux, long_name="direct + scattered shortwave irradiance")),
        "ir_incident": (("time", "facet"), ir_incident, dict(flux, long_name="longwave irradiance from the terrain")),
        "solar_direct": (("time", "facet"), solar_direct, dict(flux, long_name="direct solar irradiance")),
        "surface_temperature": (("time", "facet"), surface_temperature, {"units": "K"}),
        "sun_direction": (("time", "xyz"), sun_direction,
                          {"units": "1", "frame": "crater ENU (x east, y north, z up)"}),
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
    import xarray as xr

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
    import xarray as xr

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


def _check_time(ds, path, name: str = "time") -> None:
    if name not in ds.coords and name not in ds:
        raise FluxFileError(f"{path}: missing coordinate '{name}'")
    t = np.asarray(ds[name].values)
    if t.dtype.kind != "M":
        raise FluxFileError(f"{path}: '{name}' is not a datetime coordinate (dtype {t.dtype})")
    if t.size < 2:
        raise FluxFileError(f"{path}: '{name}' needs at least 2 samples, has {t.size}")
    if np.any(np.isnat(t)):
        raise FluxFileError(f"{path}: '{name}' has missing values")
    if np.any(np.diff(t) <= np.timedelta64(0, "ns")):
        i = int(np.argmax(np.diff(t) <= np.timedelta64(0, "ns")))
        raise FluxFileError(f"{path}: '{name}' is not strictly increasing at index {i + 1} ({t[i + 1]})")


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

    The optional spin-up window (``spinup_solar_incident``, ``spinup_ir_incident`` on ``spinup_time``,
    ending at the first ``time``) is checked the same way when present.

    Raises :class:`FluxFileError` naming the problem: unreadable file, missing variable, wrong dims or
    units, NaN/inf, negative irradiance, non-monotonic time, albedo/emissivity attributes out of range.
    """
    ds = _open(path, "flux")
    groups = [("time", ("solar_incident", "ir_incident"))]
    if "spinup_solar_incident" in ds or "spinup_ir_incident" in ds:
        groups.append(("spinup_time", ("spinup_solar_incident", "spinup_ir_incident")))
    for time_name, names in groups:
        _check_time(ds, path, time_name)
        for name in names:
            _check_var(ds, path, name, (time_name, "facet"), FLUX_UNITS)
            if np.any(ds[name].values < 0):
                raise FluxFileError(f"{path}: negative irradiance in {name}")
    if len(groups) > 1 and ds["spinup_time"].values[-1] > ds["time"].values[0]:
        raise FluxFileError(f"{path}: 'spinup_time' must end at or before the first 'time' "
                            f"({ds['spinup_time'].values[-1]} > {ds['time'].values[0]})")
    for name in ("solar_absorbed", "spinup_solar_absorbed"):  # optional: incidence-dependent albedo
        if name in ds:
            if ds[name].attrs.get("units") not in FLUX_UNITS:
                raise FluxFileError(f"{path}: '{name}' has units {ds[name].attrs.get('units')!r}, "
                                    f"expected {FLUX_UNITS[0]!r}")
            v = ds[name].values
            if not np.all(np.isfinite(v)) or np.any(v < 0):
                raise FluxFileError(f"{path}: '{name}' has NaN/inf or negative values")
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
