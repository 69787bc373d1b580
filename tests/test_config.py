"""Tests for crater_thermal.config: every committed case loads; every error path names its key."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from crater_thermal import config
from crater_thermal.config import Case, load_case, loads_case
from crater_thermal.constants import YEAR
from crater_thermal.errors import ConfigError, EphemerisRangeError

from conftest import REPO

# cases/sites/ point at DEMs the user downloads (tests/test_terrain.py loads them with a stand-in DEM)
CASE_FILES = sorted(p for p in (REPO / "cases").rglob("*.toml") if "sites" not in p.relative_to(REPO).parts)

MINIMAL = """\
[crater]
diameter_km = 2.0
[location]
lat_deg = -85.0
[period]
start = "2019-01-01"
end = "2019-03-01"
"""


def _with(section: str, line: str, base: str = MINIMAL) -> str:
    """``base`` with ``line`` added to ``[section]`` (appended as a new section if absent)."""
    if f"[{section}]\n" in base:
        return base.replace(f"[{section}]\n", f"[{section}]\n{line}\n")
    return base + f"[{section}]\n{line}\n"


def test_case_files_exist():
    names = {p.relative_to(REPO / "cases").as_posix() for p in CASE_FILES}
    assert "default.toml" in names and "validation/hayne2017_equator.toml" in names
    assert {f"thesis/crater_lat{n}S.toml" for n in (80, 82, 84, 86, 88, 90)} <= names
    assert {f"thesis/faithful/crater_lat{n}S_faithful.toml" for n in (80, 82, 84, 86, 88, 90)} <= names


@pytest.mark.parametrize("path", CASE_FILES, ids=lambda p: p.relative_to(REPO / "cases").as_posix())
def test_every_case_file_loads(path):
    case = load_case(path)
    assert isinstance(case, Case)
    assert case.toml_text == path.read_text()
    assert case.period.end > case.period.start
    assert case.path == path.resolve()


def test_thesis_cases_match_section_7_2():
    converged = sorted((REPO / "cases" / "thesis").glob("*.toml"))  # what `make thesis` globs
    craters = [load_case(p) for p in converged if p.name.startswith("crater")]
    flats = [load_case(p) for p in converged if p.name.startswith("flat")]
    assert sorted(c.location.lat_deg for c in craters) == [-90, -88, -86, -84, -82, -80]
    assert sorted(c.location.lat_deg for c in flats) == [-90, -80, -70, -60, -50, -40, -30, -20, -10, 0]
    for c in craters:
        assert (c.crater.kind, c.crater.diameter_km, c.crater.facets) == ("crater", 10.0, 502)
        assert c.period.start == np.datetime64("2019-01-01") and c.period.end == np.datetime64("2020-01-01")
        assert c.period.spinup == "periodic" and c.steps.flux_step_hours == 4.0
        assert c.surface.nominal_profile == "1300/1800" and "800/1100" in c.replay.profiles
        assert "rock" in c.replay.profiles
        assert c.replay.density_grid == ("800:2000:100" if c.location.lat_deg == -86 else None)
    assert all(f.crater.kind == "flat" for f in flats)
    for p in sorted((REPO / "cases" / "thesis" / "faithful").glob("*.toml")):
        c = load_case(p)
        assert c.period.spinup == "fixed" and c.period.initial_temperature_K is not None
        # the thesis spun up from 2016-01-01 (to 1 s)
        assert c.period.spinup_start == np.datetime64("2016-01-01T00:00:00")


def test_generated_thesis_cases_are_current(tmp_path):
    """The committed thesis files are exactly what the generator script writes."""
    script = REPO / "cases" / "generate_thesis_cases.py"
    copy = tmp_path / "cases"
    copy.mkdir()
    (copy / script.name).write_text(script.read_text())
    subprocess.run([sys.executable, str(copy / script.name)], check=True)
    made = sorted(p.relative_to(copy) for p in copy.rglob("*.toml"))
    committed = sorted(p.relative_to(REPO / "cases") for p in (REPO / "cases" / "thesis").rglob("*.toml"))
    assert made == committed
    for rel in made:
        assert (copy / rel).read_text() == (REPO / "cases" / rel).read_text(), rel


def test_defaults():
    c = loads_case(MINIMAL, name="m")
    assert c.name == "m" and c.crater.facets == 502 and c.location.lon_deg == 0.0
    assert c.period.spinup == "periodic" and c.period.spinup_years == 1.0
    assert c.steps.flux_step_s == 4 * 3600.0 and c.steps.conduction_step_s is None
    assert c.surface.albedo == 0.12 and c.surface.emissivity == 0.98 and c.surface.geothermal_flux_W_m2 == 0.033
    assert c.surface.nominal_profile == "1300/1800" and c.replay.profiles == () and c.replay.density_grid is None
    assert c.sun.moon_frame == "iau2009" and c.sun.solar_constant_W_m2 == 1361.0
    assert c.scattering.method == "exact" and c.output.checkpoint_interval_steps == 0
    assert c.period.spinup_s == YEAR
    assert c.period.duration_s == 59 * 86400.0
    fixed = loads_case(_with("period", 'spinup = "fixed"'))
    assert fixed.period.spinup_years == 3.0
    days = loads_case(_with("period", "spinup_days = 59.06"))
    assert days.period.spinup_years == pytest.approx(59.06 / 365.25)


def test_frozen_and_replace():
    c = loads_case(MINIMAL)
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.name = "x"
    d = c.replace(location=config.Location(lat_deg=-80.0))
    assert d.location.lat_deg == -80.0 and c.location.lat_deg == -85.0


def test_with_overrides_revalidates_and_records():
    c = loads_case(MINIMAL, name="m")
    d = c.with_overrides({"location.lat_deg": -80.0, "period.spinup": "fixed"}, name="m80")
    assert d.name == "m80" and d.location.lat_deg == -80.0 and d.period.spinup == "fixed"
    assert "location.lat_deg" in d.toml_text.splitlines()[0]
    assert loads_case(d.toml_text).location.lat_deg == -80.0  # the text reproduces the case
    with pytest.raises(ConfigError, match="location.lat_deg"):
        c.with_overrides({"location.lat_deg": -95.0})


def test_flat_and_mesh_kinds(tmp_path):
    flat = loads_case(MINIMAL.replace("diameter_km = 2.0", 'kind = "flat"'))
    assert flat.crater.kind == "flat" and flat.crater.diameter_km is None
    mesh_file = tmp_path / "meshes" / "m.ply"
    mesh_file.parent.mkdir()
    mesh_file.write_text("ply\n")
    case_file = tmp_path / "cases" / "c.toml"
    case_file.parent.mkdir()
    case_file.write_text(MINIMAL.replace("diameter_km = 2.0", 'mesh = "../meshes/m.ply"'))
    c = load_case(case_file)
    assert c.crater.kind == "mesh" and c.crater.mesh == mesh_file.resolve()
    assert c.name == "c"


def test_toml_dates_and_times():
    text = MINIMAL.replace('start = "2019-01-01"', "start = 2019-01-01T04:00:00Z").replace(
        'end = "2019-03-01"', "end = 2019-03-01"
    )
    c = loads_case(text)
    assert c.period.start == np.datetime64("2019-01-01T04:00") and c.period.end == np.datetime64("2019-03-01")


# ------------------------------------------------------------------ error paths
@pytest.mark.parametrize(
    "text, key",
    [
        # unknown keys at every level
        (MINIMAL + "bogus = 1\n", "bogus"),
        ("colour = 'red'\n" + MINIMAL, "colour"),
        (_with("crater", "diamter_km = 3.0"), "crater.diamter_km"),
        (_with("surface", "albdo = 0.1"), "surface.albdo"),
        (_with("output", "checkpoints = 3"), "output.checkpoints"),
        (MINIMAL + "[flat]\nlat_deg = 0\n", "flat"),
        # wrong types
        (MINIMAL.replace("diameter_km = 2.0", 'diameter_km = "2"'), "crater.diameter_km"),
        (_with("crater", "facets = 150.5"), "crater.facets"),
        (_with("crater", "facets = true"), "crater.facets"),
        (_with("sun", 'point_sun = "no"'), "sun.point_sun"),
        (_with("replay", 'profiles = "800/1100"'), "replay.profiles"),
        (_with("replay", "profiles = [800]"), "replay.profiles[0]"),
        (_with("surface", "property_set = 1"), "surface.property_set"),
        (MINIMAL.replace('start = "2019-01-01"', "start = 2019"), "period.start"),
        ("crater = 3\n" + MINIMAL.replace("[crater]\ndiameter_km = 2.0\n", ""), "crater"),
        # out of range
        (MINIMAL.replace("diameter_km = 2.0", "diameter_km = 20.0"), "crater.diameter_km"),
        (MINIMAL.replace("diameter_km = 2.0", "diameter_km = 0.0"), "crater.diameter_km"),
        (MINIMAL.replace("lat_deg = -85.0", "lat_deg = -91.0"), "location.lat_deg"),
        (_with("surface", "albedo = 1.0"), "surface.albedo"),
        (_with("surface", "emissivity = 0.0"), "surface.emissivity"),
        (_with("surface", "geothermal_flux_W_m2 = -0.01"), "surface.geothermal_flux_W_m2"),
        (_with("steps", "flux_step_hours = 0"), "steps.flux_step_hours"),
        (_with("steps", "conduction_step_s = 20000"), "steps.conduction_step_s"),
        (_with("period", "spinup_years = 0.01"), "period.spinup_years"),
        (_with("period", "spinup_days = 10"), "period.spinup_days"),
        (_with("period", "initial_temperature_K = 0"), "period.initial_temperature_K"),
        (_with("scattering", "n_bounces = 0"), "scattering.n_bounces"),
        (_with("sun", "n_rings = 0"), "sun.n_rings"),
        (_with("output", "checkpoint_interval_steps = -1"), "output.checkpoint_interval_steps"),
        # bad choices and labels
        (_with("period", 'spinup = "forever"'), "period.spinup"),
        (_with("surface", 'property_set = "martian"'), "surface.property_set"),
        (_with("sun", 'limb_darkening = "gaussian"'), "sun.limb_darkening"),
        (_with("scattering", 'method = "monte_carlo"'), "scattering.method"),
        (_with("sun", 'moon_frame = "de421"'), "sun.moon_frame"),
        (_with("surface", 'nominal_profile = "1300-1800"'), "surface.nominal_profile"),
        (_with("surface", 'nominal_profile = "50/1800"'), "surface.nominal_profile"),
        (_with("replay", 'density_grid = "800:2000"'), "replay.density_grid"),
        (_with("replay", 'density_grid = "2000:800:100"'), "replay.density_grid"),
        (MINIMAL.replace("[crater]\n", '[crater]\nkind = "flat"\n'), "crater.diameter_km"),
        # bad dates and missing keys
        (MINIMAL.replace('start = "2019-01-01"', 'start = "2019-02-30"'), "period.start"),
        (MINIMAL.replace('start = "2019-01-01"', 'start = "next year"'), "period.start"),
        (MINIMAL.replace('end = "2019-03-01"', 'end = "2018-03-01"'), "period.end"),
        (MINIMAL.replace('end = "2019-03-01"\n', ""), "period.end"),
        (MINIMAL.replace("lat_deg = -85.0\n", ""), "location.lat_deg"),
        (MINIMAL.replace("diameter_km = 2.0\n", ""), "crater.diameter_km"),
        (MINIMAL.replace("[location]\nlat_deg = -85.0\n", ""), "[location]"),
        (MINIMAL.replace("[crater]", "[crater"), "TOML"),
        (_with("period", "spinup_days = 60\nspinup_years = 1.0"), "spinup_years"),
    ],
)
def test_config_errors_name_the_key(text, key):
    with pytest.raises(ConfigError) as info:
        loads_case(text)
    msg = str(info.value)
    assert key in msg
    assert "\n" not in msg  # one line


def test_out_of_range_message_gives_value_and_range():
    with pytest.raises(ConfigError, match=r"crater\.diameter_km = 20\.0 out of range; allowed: 0 < x <= 15 \[km\]"):
        loads_case(MINIMAL.replace("diameter_km = 2.0", "diameter_km = 20.0"))


@pytest.mark.parametrize(
    "old, new, key",
    [
        ('start = "2019-01-01"', 'start = "1890-01-01"', "period.start"),
        ('end = "2019-03-01"', 'end = "2060-01-01"', "period.end"),
        ('end = "2019-03-01"', 'end = "2019-03-01"\nspinup = "fixed"\nspinup_years = 150', "period.spinup_years"),
    ],
)
def test_dates_outside_ephemeris(old, new, key):
    with pytest.raises(EphemerisRangeError) as info:
        loads_case(MINIMAL.replace(old, new))
    assert key in str(info.value) and "1899-07-30 to 2053-10-08" in str(info.value)


def test_missing_mesh_and_case_files(tmp_path):
    case_file = tmp_path / "c.toml"
    case_file.write_text(MINIMAL.replace("diameter_km = 2.0", 'mesh = "nowhere.ply"'))
    with pytest.raises(ConfigError, match=r"crater\.mesh = 'nowhere.ply': file not found"):
        load_case(case_file)
    with pytest.raises(ConfigError, match="not found"):
        load_case(tmp_path / "absent.toml")
    kern = tmp_path / "k.toml"
    kern.write_text(_with("sun", 'moon_frame = "de421"\nmoon_kernels = "no_such_dir"'))
    with pytest.raises(ConfigError, match="sun.moon_kernels"):
        load_case(kern)


def test_dump_toml_round_trip():
    c = load_case(REPO / "cases" / "default.toml")
    import tomllib

    raw = tomllib.loads(c.toml_text)
    again = loads_case(config.dump_toml(raw), name=c.name)
    assert dataclasses.replace(again, toml_text="", path=None) == dataclasses.replace(c, toml_text="", path=None)


# ------------------------------------------------------------------ one schema
def test_readme_key_table_is_generated_from_the_schema():
    """cases/README.md's key tables are what `python -m crater_thermal.config --update` writes."""
    text = (REPO / "cases" / "README.md").read_text(encoding="utf-8")
    assert config.readme_with_schema(text) == text, (
        "cases/README.md is stale: run `python -m crater_thermal.config --update cases/README.md`"
    )
    for key in config.SCHEMA:
        assert f"| `{key.name}` |" in text


def test_markdown_command_prints_the_table():
    out = subprocess.run(
        [sys.executable, "-m", "crater_thermal.config", "--markdown"],
        check=True,
        capture_output=True,
        text=True,
        cwd=REPO,
    ).stdout
    assert out == config.schema_markdown() and "### `[surface]`" in out


def test_schema_and_dataclasses_agree():
    """Every schema key with a field is a dataclass field of its section, with the schema's default."""
    for spec in config.SECTIONS:
        cls = config._SECTION_CLASSES[spec.name]
        fields = {f.name: f for f in dataclasses.fields(cls)}
        keys = [k for k in config.SCHEMA if k.section == spec.name and k.field]
        assert list(fields) == [k.name for k in keys]
        for k in keys:
            want = k.dataclass_default
            have = fields[k.name].default
            assert (have is dataclasses.MISSING) if want is config.REQUIRED else have == want, k.dotted
        assert spec.name in {f.name for f in dataclasses.fields(Case)}
    assert {k.section for k in config.SCHEMA} == {""} | {s.name for s in config.SECTIONS}


def test_config_imports_no_physics_module():
    """config is in the base layer: loading a case imports neither the physics modules nor skyfield/numba."""
    code = (
        "import sys; from crater_thermal import config; config.load_case(sys.argv[1]); "
        "print(' '.join(sorted(m for m in sys.modules if m.split('.')[0] in ('skyfield', 'numba', 'embreex')"
        " or m in ('crater_thermal.ephemeris', 'crater_thermal.thermal', 'crater_thermal.materials'))))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(REPO / "cases" / "default.toml")],
        check=True,
        capture_output=True,
        text=True,
        cwd=REPO,
    ).stdout
    assert out.strip() == ""


@pytest.mark.parametrize(
    "line, key, what",
    [
        ('nominal_profile = "300/1800"', "surface.nominal_profile", "500-3500"),
        ('nominal_profile = "1300/3600"', "surface.nominal_profile", "500-3500"),
        ('nominal_profile = "1800/1300"', "surface.nominal_profile", "decreases with depth"),
    ],
)
def test_profiles_are_checked_by_the_thermal_parser_at_load(line, key, what):
    """The thermal model's own limits apply when the case is loaded, not after the rays are traced."""
    with pytest.raises(ConfigError, match=what) as info:
        loads_case(_with("surface", line))
    assert key in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(ConfigError, match=r"replay\.profiles\[1\]"):
        loads_case(_with("replay", f'profiles = ["rock", {line.split(" = ")[1]}]'))
    with pytest.raises(ConfigError, match="replay.density_grid.*500-3500"):
        loads_case(_with("replay", 'density_grid = "400:2000:100"'))
    # what loads is what the thermal model accepts
    c = loads_case(_with("replay", 'profiles = ["500/3500", "hayne2017", "rock", "1500"]'))
    assert c.replay.profiles == ("500/3500", "hayne2017", "rock", "1500")
