"""Dataset schema validation, atomic writes, and the one-line errors of bad flux files."""

import os
import stat
from types import SimpleNamespace

import numpy as np
import pytest
import xarray as xr

from crater_thermal import io
from crater_thermal.errors import ConfigError, FluxFileError, OutputExistsError


def _mesh():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    return SimpleNamespace(
        vertices=v,
        faces=f,
        areas=np.array([0.5, 0.5]),
        normals=np.tile([0.0, 0.0, 1.0], (2, 1)),
        centroids=v[f].mean(axis=1),
        hash="abc123",
        meta={"kind": "flat"},
    )


def _flux(nt=5, **over):
    t = np.datetime64("2019-01-01") + np.arange(nt) * np.timedelta64(4, "h")
    s = np.full((nt, 2), 100.0)
    ds = xr.Dataset(
        {
            "solar_incident": (("time", "facet"), s, {"units": "W m-2"}),
            "ir_incident": (("time", "facet"), s / 10, {"units": "W m-2"}),
        },
        coords={"time": t},
        attrs={"albedo": 0.12, "emissivity": 0.98},
    )
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
    with pytest.raises(TypeError, match="unserialisable"):  # xarray refuses the attribute
        io.write_dataset_atomic(bad, p, overwrite=True)
    assert p.read_bytes() == before


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda ds: ds.drop_vars("ir_incident"), "missing variable 'ir_incident'"),
        (lambda ds: ds.assign(solar_incident=ds.solar_incident.assign_attrs(units="erg")), "units 'erg'"),
        (lambda ds: ds.assign(solar_incident=ds.solar_incident.where(ds.facet < 1)), "NaN"),
        (lambda ds: ds.assign_coords(time=ds.time.values[[0, 2, 1, 3, 4]]), "not strictly increasing"),
        (lambda ds: ds.assign_attrs(albedo=1.5), "albedo"),
        (lambda ds: ds.assign(ir_incident=-ds.ir_incident), "negative"),
    ],
)
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
    res = {
        "surface_temperature": np.array([200.0, 210.0]),
        "solar_direct": np.ones(2),
        "solar_incident": np.ones(2),
        "ir_incident": np.zeros(2),
    }
    p = io.write_steady(tmp_path / "s.nc", m, res, {"albedo": 0.12, "sun_elevation_deg": 10.0})
    ds = xr.open_dataset(p)
    assert ds["surface_temperature"].attrs["units"] == "K"
    assert ds.attrs["mesh_hash"] == "abc123"
    ds.close()


# ----------------------------------------------------------------------------- the one atomic writer


def _leftovers(folder):
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


def test_atomic_output_replaces_only_on_success(tmp_path):
    p = tmp_path / "sub" / "out.txt"
    with io.atomic_output(p) as tmp:
        assert tmp.parent == p.parent and tmp.name.endswith(".txt") and tmp.exists() and not p.exists()
        tmp.write_text("first")
    assert p.read_text() == "first"
    with pytest.raises(OutputExistsError, match="overwrite"):
        with io.atomic_output(p):
            raise AssertionError("the block must not run for an existing output")
    with pytest.raises(RuntimeError, match="interrupted"):
        with io.atomic_output(p, overwrite=True) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert p.read_text() == "first" and not _leftovers(p.parent)  # earlier output intact, no temporary left
    with io.atomic_output(p, overwrite=True) as tmp:
        tmp.write_text("second")
    assert p.read_text() == "second" and not _leftovers(p.parent)


def test_atomic_output_refuses_a_folder_for_a_file(tmp_path):
    (tmp_path / "d").mkdir()
    for overwrite in (False, True):
        with pytest.raises(ConfigError, match="is a folder") as err:
            with io.atomic_output(tmp_path / "d", overwrite=overwrite):
                pass
        assert "\n" not in str(err.value)
    (tmp_path / "f").write_text("x")
    with pytest.raises(ConfigError, match="is a file"):
        io.check_output(tmp_path / "f" / "out.nc")


def test_atomic_output_folder_is_replaced_whole(tmp_path):
    d = tmp_path / "figs"
    with io.atomic_output(d, folder=True) as tmp:
        (tmp / "a.png").write_text("a")
        (tmp / "b.png").write_text("b")
    with io.atomic_output(d, overwrite=True, folder=True) as tmp:
        (tmp / "a.png").write_text("new")
    assert sorted(p.name for p in d.iterdir()) == ["a.png"] and (d / "a.png").read_text() == "new"
    assert not _leftovers(tmp_path)


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_atomic_output_permissions_follow_the_umask(tmp_path, umask):
    old = os.umask(umask)
    try:
        io.write_dataset_atomic(_flux(), tmp_path / "run.nc")
        io.save_npz_atomic(tmp_path / "c.npz", a=np.zeros(3))
        with io.atomic_output(tmp_path / "d", folder=True) as tmp:
            (tmp / "x").write_text("x")
    finally:
        os.umask(old)
    for name in ("run.nc", "c.npz"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o666 & ~umask
    assert stat.S_IMODE((tmp_path / "d").stat().st_mode) == 0o777 & ~umask


def test_spinup_fluxes_are_validated_like_the_record(tmp_path):
    """A flux file's spin-up window reaches the conduction solver too: bad values must be a FluxFileError
    naming the variable, never a solver failure."""

    def with_spinup(values, end_offset_h=0):
        ds = _flux()
        ts = ds["time"].values[0] + np.timedelta64(end_offset_h, "h") - np.arange(3, -1, -1) * np.timedelta64(4, "h")
        ds = ds.assign_coords(spinup_time=ts)
        for name in ("spinup_solar_incident", "spinup_ir_incident"):
            ds[name] = (("spinup_time", "facet"), np.array(values, float), {"units": "W m-2"})
        return ds

    good = [[10.0, 10.0]] * 4
    io.write_dataset_atomic(with_spinup(good), tmp_path / "ok.nc")
    assert "spinup_solar_incident" in io.read_flux_dataset(tmp_path / "ok.nc")
    for values, offset, message in (
        (good[:3] + [[np.nan, 1.0]], 0, "spinup_solar_incident.*NaN"),
        (good[:3] + [[-1.0, 1.0]], 0, "negative irradiance in spinup_solar"),
        (good, 4, "must end at or before"),
    ):
        p = tmp_path / "bad.nc"
        io.write_dataset_atomic(with_spinup(values, offset), p, overwrite=True)
        with pytest.raises(FluxFileError, match=message):
            io.read_flux_dataset(p)
