"""Dataset schema validation, atomic writes, and the one-line errors of bad flux files."""

from types import SimpleNamespace

import numpy as np
import pytest
import xarray as xr

from crater_thermal import io
from crater_thermal.errors import FluxFileError, OutputExistsError


def _mesh():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    return SimpleNamespace(vertices=v, faces=f, areas=np.array([0.5, 0.5]),
                           normals=np.tile([0.0, 0.0, 1.0], (2, 1)), centroids=v[f].mean(axis=1),
                           hash="abc123", meta={"kind": "flat"})


def _flux(nt=5, **over):
    t = np.datetime64("2019-01-01") + np.arange(nt) * np.timedelta64(4, "h")
    s = np.full((nt, 2), 100.0)
    ds = xr.Dataset({"solar_incident": (("time", "facet"), s, {"units": "W m-2"}),
                     "ir_incident": (("time", "facet"), s / 10, {"units": "W m-2"})},
                    coords={"time": t}, attrs={"albedo": 0.12, "emissivity": 0.98})
    for k, v in over.items():
        ds[k] = v
    return ds


def test_roundtrip_and_refuse_overwrite(tmp_path):
    p = tmp_path / "f.nc"
    io.write_dataset_atomic(_flux(), p)
    ds = io.read_flux_dataset(p)
    assert ds.sizes["time"] == 5
    np.testing.assert_array_equal(ds["solar_incident"].values, 100.0)
    before = p.read_bytes()
    with pytest.raises(OutputExistsError):
        io.write_dataset_atomic(_flux(nt=7), p)
    assert p.read_bytes() == before  # the earlier result is untouched
    io.write_dataset_atomic(_flux(nt=7), p, overwrite=True)
    assert io.read_flux_dataset(p).sizes["time"] == 7
    assert not [x for x in tmp_path.iterdir() if x.name.startswith(".")]  # no temporary left behind


def test_failed_write_leaves_old_file(tmp_path):
    p = tmp_path / "f.nc"
    io.write_dataset_atomic(_flux(), p)
    before = p.read_bytes()
    bad = _flux()
    bad.attrs["unserialisable"] = object()
    with pytest.raises(Exception):
        io.write_dataset_atomic(bad, p, overwrite=True)
    assert p.read_bytes() == before


@pytest.mark.parametrize("mutate, message", [
    (lambda ds: ds.drop_vars("ir_incident"), "missing variable 'ir_incident'"),
    (lambda ds: ds.assign(solar_incident=ds.solar_incident.assign_attrs(units="erg")), "units 'erg'"),
    (lambda ds: ds.assign(solar_incident=ds.solar_incident.where(ds.facet < 1)), "NaN"),
    (lambda ds: ds.assign_coords(time=ds.time.values[[0, 2, 1, 3, 4]]), "not strictly increasing"),
    (lambda ds: ds.assign_attrs(albedo=1.5), "albedo"),
    (lambda ds: ds.assign(ir_incident=-ds.ir_incident), "negative"),
])
def test_bad_flux_files(tmp_path, mutate, message):
    p = tmp_path / "bad.nc"
    mutate(_flux()).to_netcdf(p)
    with pytest.raises(FluxFileError, match=message):
        io.read_flux_dataset(p)


def test_corrupt_and_missing_file(tmp_path):
    p = tmp_path / "corrupt.nc"
    p.write_bytes(b"not a netcdf file at all")
    with pytest.raises(FluxFileError, match="cannot read"):
        io.read_flux_dataset(p)
    with pytest.raises(FluxFileError, match="does not exist"):
        io.read_flux_dataset(tmp_path / "nope.nc")


def test_write_steady(tmp_path):
    m = _mesh()
    res = {"surface_temperature": np.array([200.0, 210.0]), "solar_direct": np.ones(2),
           "solar_incident": np.ones(2), "ir_incident": np.zeros(2)}
    p = io.write_steady(tmp_path / "s.nc", m, res, {"albedo": 0.12, "sun_elevation_deg": 10.0})
    ds = xr.open_dataset(p)
    assert ds["surface_temperature"].attrs["units"] == "K"
    assert ds.attrs["mesh_hash"] == "abc123"
    ds.close()
