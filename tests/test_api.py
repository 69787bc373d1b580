"""The Python API (issue 21): a whole case through ``crater_thermal`` in a fresh interpreter gives the CLI's
run.nc; replays, analysis and reports the same; the package import stays cheap; typed errors."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_process import cli

import crater_thermal as ct
from crater_thermal import io
from crater_thermal.errors import ConfigError, ProfileError

REPO = Path(__file__).resolve().parents[1]

SECTIONS = {
    "crater": {"kind": "crater", "diameter_km": 2.0, "facets": 60},
    "location": {"lat_deg": -85.0, "lon_deg": 0.0},
    "period": {"start": "2019-01-01", "end": "2019-01-31", "spinup": "periodic", "spinup_days": 29.53},
    "steps": {"flux_step_hours": 4.0},
}
CASE_TOML = """
name = "api"
[crater]
kind = "crater"
diameter_km = 2.0
facets = 60
[location]
lat_deg = -85.0
lon_deg = 0.0
[period]
start = "2019-01-01"
end = "2019-01-31"
spinup = "periodic"
spinup_days = 29.53
[steps]
flux_step_hours = 4.0
"""
#: Series compared between the API's Dataset and the CLI's run.nc.
SERIES = ("solar_incident", "solar_direct", "ir_incident", "surface_temperature")


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The same case through the CLI (run, replay, report) and through the API in a fresh interpreter."""
    d = tmp_path_factory.mktemp("api")
    case = d / "api.toml"
    case.write_text(CASE_TOML)
    for args in (
        ("run", case, "-o", d / "cli_run.nc"),
        ("replay", d / "cli_run.nc", "--profile", "800/1100", "--profile", "rock", "-o", d / "cli_replay.nc"),
        ("report", d / "cli_run.nc", d / "cli_replay.nc", "-o", d / "report", "--no-snapshots"),
    ):
        r = cli(*args)
        assert r.returncode == 0, r.stderr
    script = f"""
import warnings, json
warnings.simplefilter("ignore")
import crater_thermal as ct
run = ct.run(ct.load_case({str(case)!r}))          # in memory
rep = ct.replay(run, profiles=["800/1100", "rock"])
res = ct.analyse(run, rep)
run.to_netcdf({str(d / "api_run.nc")!r})
rep.to_netcdf({str(d / "api_replay.nc")!r})
json.dump(res.summary, open({str(d / "api_summary.json")!r}, "w"))
"""
    r = subprocess.run(
        [sys.executable, "-c", script],
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    return d


def test_api_run_in_a_fresh_interpreter_equals_the_cli_run(made):
    a, b = io.open_run(made / "api_run.nc"), io.open_run(made / "cli_run.nc")
    assert a.sizes == b.sizes
    np.testing.assert_array_equal(a["time"].values, b["time"].values)
    np.testing.assert_array_equal(a["mesh_vertices"].values, b["mesh_vertices"].values)
    for name in SERIES:
        # the same code on the same input: identical up to the summation order of threaded IR products
        # (float64 inside, stored as float32: 1e-6 K / 1e-6 W m-2 is far below float32's ~1e-5 at 100 K)
        np.testing.assert_allclose(a[name].values, b[name].values, rtol=0, atol=1e-6, err_msg=name)
    for key in ("case_name", "lat_deg", "nominal_profile", "start_method", "mesh_hash"):
        assert a.attrs.get(key) == b.attrs.get(key), key


def test_api_replay_and_analysis_equal_the_cli(made):
    a, b = io.open_replay(made / "api_replay.nc"), io.open_replay(made / "cli_replay.nc")
    assert list(a["profile"].values) == list(b["profile"].values)
    np.testing.assert_allclose(a["surface_temperature"].values, b["surface_temperature"].values, rtol=0, atol=1e-6)
    api_s = json.loads((made / "api_summary.json").read_text())
    cli_s = json.loads((made / "report" / "summary.json").read_text())
    for key in ("night_median_dT_K", "night_median_T_nominal_K", "max_abs_night_median_dT_K", "loose_profile"):
        assert json.dumps(api_s[key], sort_keys=True) == json.dumps(cli_s[key], sort_keys=True), key


def test_case_from_dict_is_the_case_file(tmp_path):
    path = tmp_path / "api.toml"
    path.write_text(CASE_TOML)
    a = ct.case_from_dict(SECTIONS, name="api")
    b = ct.load_case(path)
    for section in ("crater", "location", "period", "steps", "surface", "sun", "scattering", "radiation"):
        assert getattr(a, section) == getattr(b, section), section
    c = ct.load_case(path, {"location.lat_deg": -80.0, "period.end": "2019-01-10"})
    assert c.location.lat_deg == -80.0 and str(c.period.end).startswith("2019-01-10")


def test_run_to_a_file_streams_and_reports_progress(tmp_path):
    case = ct.case_from_dict(
        {**SECTIONS, "period": {"start": "2019-01-01", "end": "2019-01-04", "spinup": "fixed", "spinup_days": 1.0}},
        name="small",
    )
    stages = []
    ds = ct.run(case, tmp_path / "run.nc", progress=ct.progress_callback(lambda s, d, t: stages.append((s, d, t))))
    with ds:
        assert ds["surface_temperature"].shape[1] == 60 and (tmp_path / "run.nc").is_file()
    names = {s for s, _, _ in stages}
    assert any(n.startswith("record") for n in names) and any(n.startswith("sunlight") for n in names)
    assert all(0 <= d <= t for _, d, t in stages)
    with pytest.raises(Exception) as exc:
        ct.run(case, tmp_path / "run.nc")
    assert "exists" in str(exc.value)


def test_errors_are_the_typed_ones(tmp_path):
    with pytest.raises(ConfigError):
        ct.case_from_dict({"crater": {"kind": "crater", "diameter_km": -1.0}})
    with pytest.raises(ConfigError, match="progress"):
        ct.run(ct.case_from_dict(SECTIONS), progress="yes please")
    with pytest.raises(ProfileError, match="allow-inverted"):
        ct.replay(tmp_path / "missing.nc", profiles=["1800/1300"])


def test_package_import_is_cheap_and_names_do_not_collide():
    code = (
        "import sys, crater_thermal as ct\n"
        "heavy = [m for m in ('crater_thermal.simulate', 'numba', 'xarray') if m in sys.modules]\n"
        "import crater_thermal.report, crater_thermal.sweep\n"
        "print(heavy, callable(ct.make_report), callable(ct.run_sweep), callable(ct.run))\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True
    )
    assert r.stdout.strip() == "[] True True True", r.stderr
    assert set(ct.__all__) <= set(dir(ct))


def test_steady_state_from_a_mesh_object_equals_the_cli(tmp_path):
    """ct.steady_state on a Mesh (in memory) and `crater-thermal steady` on its file give the same field."""
    mesh = ct.mesh_bowl(depth_to_diameter=0.2, facets=400, diameter_m=1000.0)
    ct.save_mesh(mesh, tmp_path / "bowl.ply")
    ds = ct.steady_state(mesh, 20.0, 0.0, point_sun=True)
    r = cli("steady", tmp_path / "bowl.ply", "--sun-elevation-deg", "20", "--sun-azimuth-deg", "0", "--point-sun")
    assert r.returncode == 2  # -o is required: the CLI refuses, the API writes nothing without out
    r = cli(
        "steady",
        tmp_path / "bowl.ply",
        "--sun-elevation-deg",
        "20",
        "--sun-azimuth-deg",
        "0",
        "--point-sun",
        "-o",
        tmp_path / "s.nc",
    )
    assert r.returncode == 0, r.stderr
    with io.open_written(tmp_path / "s.nc") as ref:
        np.testing.assert_allclose(ds["surface_temperature"].values, ref["surface_temperature"].values, atol=1e-9)
    assert ds.attrs["view_factors"] == "exact" and float(ds["surface_temperature"].min()) > 0
