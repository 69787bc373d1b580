"""Tests of crater_thermal.report: the report renders from a small synthetic run/replay, and refuses bad input."""

import contextlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from crater_thermal import report as rp
from crater_thermal.errors import FluxFileError, OutputExistsError

from synthetic import make_replay, make_run

ENV = {
    **os.environ,
    "PYTHONPATH": str(rp.Path(rp.__file__).resolve().parents[1]),
    "VTK_DEFAULT_OPENGL_WINDOW": os.environ.get("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow"),
}


def cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "crater_thermal", *map(str, args)], capture_output=True, text=True, env=ENV, timeout=120
    )


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("data")
    run = make_run(lat_deg=-86.0, n_lunar_days=1.5, n_rings=8)
    rep = make_replay(run)
    run.to_netcdf(d / "run.nc")
    rep.to_netcdf(d / "replay.nc")
    return d, run, rep


@pytest.fixture(scope="module")
def made_report(files):
    """The module's report (3-D snapshots on), drawn once, and the progress calls it made: ``rp.bar`` is replaced
    by a recorder while it is drawn, so that the progress test counts the steps of this report instead of
    drawing another (the steps do not depend on the snapshots: only profiles, figures and the summary count)."""
    d, _, _ = files
    out = d / "rep"
    calls = []

    @contextlib.contextmanager
    def bar(description, flag=None):
        yield lambda done, total: calls.append((done, total))

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rp, "bar", bar)
        path = rp.make_report(d / "run.nc", d / "replay.nc", out, progress=True)
    assert path == out / "report.html"
    return out, calls


@pytest.fixture(scope="module")
def report_dir(made_report):
    return made_report[0]


def _strict_json(path):
    def no_nan(c):
        raise AssertionError(f"non-JSON constant {c} in {path}")

    return json.loads(path.read_text(), parse_constant=no_nan)


def test_summary_has_exactly_the_documented_keys(report_dir):
    s = _strict_json(report_dir / "summary.json")
    assert set(s) == set(rp.SUMMARY_KEYS)
    assert all(isinstance(v, str) and v for v in rp.SUMMARY_KEYS.values())
    assert s["loose_profile"] == "800/1100" and s["rock_profile"] == "rock"
    assert (
        set(s["detection"]) == set(s["instruments"]) == {"diviner_ch7", "diviner_ch8", "diviner_ch9", "microbolometer"}
    )
    assert all(set(per) == set(s["regions"]) for per in s["detection"].values())
    assert s["schema_version"] == 2


def test_html_is_self_contained_and_references_every_figure(report_dir):
    s = _strict_json(report_dir / "summary.json")
    html = (report_dir / "report.html").read_text()
    on_disk = sorted(p.name for p in (report_dir / "figures").glob("*.png"))
    assert sorted(s["figures"]) == on_disk
    assert set(rp.FIGURES) <= set(on_disk)
    for name in on_disk:
        assert f"figures/{name}" in html
    # every image is embedded (readable offline), none loaded from disk
    assert html.count("<img ") == len(on_disk) == html.count("src='data:image/png;base64,")


def test_pngs_are_not_blank(report_dir):
    for p in (report_dir / "figures").glob("*.png"):
        assert p.stat().st_size > 1000
        img = np.asarray(Image.open(p).convert("L"), dtype=float)
        assert img.var() > 0, p.name


def test_snapshots_rendered_here(report_dir):
    s = _strict_json(report_dir / "summary.json")
    # this machine renders headless through EGL; the snapshots must then be in the report
    assert s["snapshot_note"] is None
    assert {"map3d_temperature.png", "map3d_night_dT.png"} <= set(s["figures"])


def test_summary_values_match_an_independent_computation(report_dir, files):
    _, run, rep = files
    s = _strict_json(report_dir / "summary.json")
    meta = json.loads(run.attrs["mesh_meta"])
    c = run["centroid"].values
    floor = np.hypot(c[:, 0], c[:, 1]) <= meta["floor_radius_m"]
    night = run["sun_direction"].values[:, 2] < 0
    # the "dark" night (the report's default since issue 25; before it the direct-only "facet" night, which
    # made every floor sample from 24 h on night): the synthetic floor is never directly lit but receives
    # scattered light whenever any facet is lit, so a floor sample is night when no sample in the 24 h + one
    # step before it (fluxes are linear between samples) had more than the dark threshold, and it is at least
    # 24 h after the record's start (the history before it counts as lit)
    assert not (run["solar_direct"].values[:, floor] > 0).any()
    hours = (run["time"].values - run["time"].values[0]) / np.timedelta64(1, "h")
    step_h = hours[1] - hours[0]
    lit = run["solar_incident"].values[:, floor] > s["night_threshold_W_m2"]
    floor_night = np.array(
        [
            [
                h >= 24.0 and not lit[(hours > h - 24.0 - step_h - 1e-6) & (hours <= h), j].any()
                for j in range(lit.shape[1])
            ]
            for h in hours
        ]
    )
    assert floor_night.any() and s["night_fallback_facets"] == 0  # the -86 deg floor is dark for days
    T = rep["surface_temperature"]
    d = (T.sel(profile="800/1100") - T.sel(profile="1300/1800")).values
    expect = np.median(d[:, floor][floor_night])
    # same numbers through a different path: agreement to float rounding (1e-9 K)
    assert s["night_definition"] == "dark" and s["night_min_dark_hours"] == 24.0
    assert s["night_threshold_W_m2"] == 1e-3 and s["night_fallback_fraction"] == 0.1
    assert s["night_median_dT_K"]["800/1100"]["floor"] == pytest.approx(expect, abs=1e-9)
    assert s["night_fraction"] == pytest.approx(night.mean())
    assert s["region_facet_count"]["floor"] == int(floor.sum())
    grid = s["density_grid_floor_night_median_dT_K"]
    i, j = grid["rho_top_kg_m3"].index(800.0), grid["rho_bottom_kg_m3"].index(1100.0)
    assert grid["dT_K"][i][j] == pytest.approx(expect, abs=1e-9)
    det = s["detection"]["diviner_ch9"]["floor"]
    assert det["dT_median_K"] == pytest.approx(expect, abs=1e-9)
    assert det["detectable"] == (det["dwell_s"] is not None)
    assert det["limiting_term"] in ("instrument_white", "allan_floor", "natural_scatter", "gain_error")
    assert len(det["pd_vs_dwell"]) == len(s["detection_dwell_grid_s"]["diviner_ch9"])
    assert 0.0 <= det["best_local_time_h"] < 24.0
    # the microbolometer receives ~nothing from a night floor: its NETD there is tens of K (the synthetic
    # floor's per-facet night includes the day's indirect heating, ~70 K) to thousands of K (at ~50 K)
    band = s["band_signal_night_floor"]["microbolometer"]
    assert band["netd_K"][0] > 10 * abs(expect) and not s["detection"]["microbolometer"]["floor"]["detectable"]
    assert s["detection"]["microbolometer"]["floor"]["dwell_s_no_scatter"] is None


def test_refuses_existing_report_and_overwrites_atomically(report_dir, files):
    d, run, rep = files
    with pytest.raises(OutputExistsError, match="overwrite"):
        rp.make_report(run, rep, report_dir, progress=False, snapshots=False)
    before = (report_dir / "summary.json").stat().st_mtime_ns
    rp.make_report(run, rep, report_dir, overwrite=True, progress=False, snapshots=False)
    s = _strict_json(report_dir / "summary.json")
    assert (report_dir / "summary.json").stat().st_mtime_ns >= before
    assert s["snapshot_note"] == "3-D snapshots not requested"
    assert sorted(p.name for p in (report_dir / "figures").glob("*.png")) == sorted(s["figures"])
    assert not [p for p in d.iterdir() if p.name.startswith(".")]  # no temporary folders left behind


def test_report_survives_a_rendering_failure(files, tmp_path, monkeypatch):
    _, run, rep = files
    from crater_thermal import viz

    def broken(*a, **k):
        raise RuntimeError("no OpenGL context")

    monkeypatch.setattr(viz, "snapshot", broken)
    rp.make_report(run, rep, tmp_path / "r", progress=False)
    s = _strict_json(tmp_path / "r" / "summary.json")
    assert "no OpenGL context" in s["snapshot_note"]
    assert "no OpenGL context" in (tmp_path / "r" / "report.html").read_text()
    assert set(rp.FIGURES) == set(s["figures"])


def test_several_latitudes(files, tmp_path):
    _, run, rep = files
    run2 = make_run(lat_deg=-80.0, n_lunar_days=1.0, n_rings=8)
    # progress=True: the rich bar must also work (here on a captured, non-terminal stream)
    rp.make_report([run, run2], [rep, make_replay(run2)], tmp_path / "r", progress=True, snapshots=False)
    s = _strict_json(tmp_path / "r" / "summary.json")
    assert set(s["latitude_night_median_dT_K"]) == {"-86", "-80"} == set(s["latitude_detection_dwell_s"])
    assert set(s["latitude_detection_dwell_s"]["-80"]) == set(s["instruments"])


def test_cli_report_takes_a_sweep_folder_and_a_user_band(files, tmp_path):
    d, run, rep = files
    sweep = tmp_path / "sweep"
    for name, r in (("lat86S", run), ("lat80S", make_run(lat_deg=-80.0, n_lunar_days=1.0, n_rings=8))):
        (sweep / name).mkdir(parents=True)
        r.to_netcdf(sweep / name / "run.nc")
        (rep if r is run else make_replay(r)).to_netcdf(sweep / name / "replay.nc")
    (sweep / "unfinished").mkdir()  # a case without outputs is skipped
    out = cli(
        "report",
        sweep,
        "-o",
        tmp_path / "r",
        "--no-snapshots",
        "--instrument",
        "diviner_ch9",
        "--band-um",
        "8:14",
        "--netd-k",
        "0.05",
        "--reference-footprints",
        "4",
    )
    assert out.returncode == 0, out.stderr
    s = _strict_json(tmp_path / "r" / "summary.json")
    assert set(s["latitude_night_median_dT_K"]) == {"-86", "-80"}
    assert set(s["instruments"]) == {"diviner_ch9", "custom"} and s["observation"]["reference_footprints"] == 4
    bad = cli("report", tmp_path / "r", "-o", tmp_path / "r2")
    assert bad.returncode == 2 and "sweep" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


#: Diviner footprint [m2]
DIVINER_FOOTPRINT_M2 = 240.0 * 480.0


@pytest.fixture(scope="module")
def cli_patch_report(files, tmp_path_factory):
    """One ``crater-thermal report`` run through a pipe (stdout and stderr captured: not a terminal), with a
    patch area, a footprint area, two instruments and passes; its folder and CompletedProcess. Shared by the
    quiet-output test and the observing-mode test (the progress output depends only on stderr not being a
    terminal, not on the observation options)."""
    d, _, _ = files
    out_dir = tmp_path_factory.mktemp("cli_report") / "r"
    a = DIVINER_FOOTPRINT_M2
    out = cli(
        "report", d / "run.nc", d / "replay.nc", "-o", out_dir, "--no-snapshots",
        "--instrument", "diviner_ch9", "--instrument", "microbolometer",
        "--patch-area-m2", 3.5 * a, "--footprint-area-m2", a, "--reference-footprints", "3", "--passes", "40",
    )  # fmt: skip
    return out_dir, out


def test_cli_report_quiet_when_not_a_terminal(cli_patch_report):
    r_dir, out = cli_patch_report
    assert out.returncode == 0, out.stderr
    # no progress bar on a pipe: at most plain progress lines (one per 30 s of a stage)
    assert all(line.startswith("progress: ") for line in out.stderr.splitlines()), out.stderr
    assert (r_dir / "report.html").is_file()


def test_cli_report_states_the_patch_and_the_observing_mode(files, cli_patch_report, tmp_path):
    """Issue 25: a patch area and footprint area give k; Diviner is observed in passes, the camera stares;
    summary.json's observation block and each detection row say which, and in what unit."""
    d, _, _ = files
    r_dir, out = cli_patch_report
    a = DIVINER_FOOTPRINT_M2
    assert out.returncode == 0, out.stderr
    s = _strict_json(r_dir / "summary.json")
    o = s["observation"]
    assert (o["candidate_footprints"], o["reference_footprints"], o["passes"], o["mode"]) == (3, 3, 40, "auto")
    assert o["patch_area_m2"] == pytest.approx(3.5 * a) and o["footprint_area_m2"] == pytest.approx(a)
    assert o["mode_by_instrument"] == {"diviner_ch9": "passes", "microbolometer": "stare"}
    assert o["pass_integration_s_by_instrument"] == {"diviner_ch9": 0.128, "microbolometer": None}
    ch9 = s["detection"]["diviner_ch9"]["floor"]
    assert ch9["mode"] == "passes" and ch9["exposure_unit"] == "passes"
    # the synthetic floor's night contrast, 3 vs 3 footprints: detectable within the passes searched
    assert ch9["detectable"] and ch9["exposure"] == ch9["passes"] and f"{ch9['passes']} passes" in ch9["answer"]
    assert ch9["dwell_s"] == pytest.approx(ch9["passes"] * 0.128)
    grid = np.asarray(s["detection_dwell_grid_s"]["diviner_ch9"]) / 0.128  # whole passes
    np.testing.assert_allclose(grid, np.round(grid), atol=1e-9)
    assert s["detection"]["microbolometer"]["floor"]["exposure_unit"] == "s"
    page = (r_dir / "report.html").read_text()
    assert "Candidate patch of 3 footprint(s)" in page and "passes for P_D" in page
    bad = cli("report", d / "run.nc", d / "replay.nc", "-o", tmp_path / "r2", "--patch-area-m2", "1e5")
    assert bad.returncode != 0 and "footprint_area_m2" in bad.stderr


@pytest.mark.parametrize(
    "case, match",
    [
        ("hash", "mesh_hash"),
        ("time", "time axis"),
        ("missing", "sun_direction"),
        ("nofile", "does not exist"),
    ],
)
def test_cli_bad_input_one_line_exit_2(files, tmp_path, case, match):
    d, run, rep = files
    run_p, rep_p = d / "run.nc", d / "replay.nc"
    if case == "hash":
        bad = rep.copy()
        bad.attrs["mesh_hash"] = "ffffffffffffffff"
        rep_p = tmp_path / "bad.nc"
        bad.to_netcdf(rep_p)
    elif case == "time":
        rep_p = tmp_path / "bad.nc"
        rep.isel(time=slice(0, 20)).to_netcdf(rep_p)
    elif case == "missing":
        run_p = tmp_path / "bad.nc"
        run.drop_vars("sun_direction").to_netcdf(run_p)
    else:
        run_p = tmp_path / "nothing.nc"
    out = cli("report", run_p, rep_p, "-o", tmp_path / "r")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and match in lines[0], out.stderr
    assert not (tmp_path / "r").exists()


def test_foreign_replay_raises_flux_file_error(files):
    _, run, rep = files
    bad = rep.copy()
    bad.attrs["mesh_hash"] = "ffffffffffffffff"
    with pytest.raises(FluxFileError, match="mesh_hash"):
        rp.make_report(run, bad, "never_written", progress=False)
    assert not os.path.exists("never_written")


def test_analysis_and_report_do_not_import_xarray_or_pyvista():
    code = (
        "import sys, crater_thermal.analysis, crater_thermal.report, crater_thermal.viz, crater_thermal.cli;"
        "bad = [m for m in ('xarray', 'pyvista') if m in sys.modules]; assert not bad, bad"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=60)
    assert out.returncode == 0, out.stderr


def test_report_without_pyvista_skips_snapshots_with_a_note(files, tmp_path, monkeypatch, capsys):
    _, run, rep = files
    monkeypatch.setitem(sys.modules, "pyvista", None)  # as if the viz extra were not installed
    rp.make_report(run, rep, tmp_path / "r", progress=False)
    s = _strict_json(tmp_path / "r" / "summary.json")
    assert set(rp.FIGURES) == set(s["figures"])  # every matplotlib figure, no 3-D snapshot
    assert "pip install 'crater_thermal[viz]'" in s["snapshot_note"]
    err = capsys.readouterr().err
    assert err.startswith("note: 3-D snapshots skipped") and err.count("\n") == 1


def test_report_progress_callback_counts_every_step(files, made_report):
    _, _, rep = files
    _, calls = made_report  # the progress calls of the module's report (progress=True, a recording bar)
    n_profiles = len(rep["profile"]) - 1  # every profile but the nominal one
    total = n_profiles + len(rp.FIGURES) + 1
    assert calls == [(k, total) for k in range(1, total + 1)]
