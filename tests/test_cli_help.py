"""The terminal (issue 20): every option's unit and syntax visible in --help, flags without a metavar,
--version, progress lines in a log, one-line warnings from sweep workers, option names in messages."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import typer.main

from crater_thermal import __version__
from crater_thermal.cli import app

REPO = Path(__file__).resolve().parents[1]

#: Option-name suffix -> the unit its help must show, as written in the help text.
SUFFIX_UNITS = {
    "_deg": "[deg]",
    "_km": "[km]",
    "_m": "[m]",
    "_s": "[s]",
    "_k": "[K]",
    "_um": "[um]",
    "_hours": "[h]",
}
#: Options whose quantity has a unit their name does not spell.
NAMED_UNITS = {
    "solar_constant": "[W m-2]",
    "replay profile": "[kg m-3]",
    "show profile": "[K]",
    "density_grid": "[kg m-3]",
    "initial_temperature": "[K]",
    "center_lat": "[deg]",
    "center_lon": "[deg]",
    "roughness": "[m]",
    "export profile": "[kg m-3]",
    "export variable": "[K]",
}


def cli(*args, **extra):
    return subprocess.run(
        [sys.executable, "-m", "crater_thermal", *map(str, args)],
        env=dict(os.environ, PYTHONPATH=str(REPO), COLUMNS="100", **extra),
        capture_output=True,
        text=True,
        timeout=600,
    )


def commands(group=None, path=()):
    """(command path, click command) of every leaf command."""
    group = group or typer.main.get_command(app)
    for name, sub in getattr(group, "commands", {}).items():
        if getattr(sub, "commands", None):
            yield from commands(sub, (*path, name))
        else:
            yield (*path, name), sub


ALL = list(commands())


def test_every_command_is_walked():
    names = {" ".join(p) for p, _ in ALL}
    assert {"run", "replay", "report", "steady", "mesh crater", "mesh dem", "dem synth", "cache info"} <= names


def expected_unit(command: str, name: str):
    for key in (f"{command} {name}", name):
        if key in NAMED_UNITS:
            return NAMED_UNITS[key]
    for suffix, unit in SUFFIX_UNITS.items():
        if name.endswith(suffix):
            return unit
    return None


@pytest.mark.parametrize("path, command", ALL, ids=[" ".join(p) for p, _ in ALL])
def test_help_shows_units_and_no_bool_metavar(path, command):
    r = cli(*path, "--help")
    assert r.returncode == 0, r.stderr
    assert "<bool>" not in r.stdout
    # each option's entry: its first line starts "  -" (two spaces), wrapped lines are indented deeper;
    # joined with single spaces, so that a unit wrapped over two lines still reads
    entries, current = {}, None
    for line in r.stdout.splitlines():
        m = re.match(r"^  (-\w, )?(--[\w-]+)", line)
        if m:
            current = m.group(2)
            entries[current] = line
        elif current and line.startswith("   "):
            entries[current] += " " + line.strip()
        else:
            current = None
    entries = {k: " ".join(v.split()) for k, v in entries.items()}
    for param in command.params:
        if getattr(param, "param_type_name", "") != "option" or param.name == "help":
            continue
        assert param.help, f"{' '.join(path)} {param.opts[0]} has no help"
        long_flag = [o for o in param.opts if o.startswith("--")][0]
        assert long_flag in entries, f"{' '.join(path)} {long_flag} missing from --help"
        unit = expected_unit(" ".join(path), param.name)
        if unit is not None:
            assert unit in entries[long_flag], f"{' '.join(path)} {long_flag}: {unit} not shown in --help"


def test_crater_syntax_is_visible():
    text = " ".join(cli("dem", "synth", "--help").stdout.split())
    assert "D_KM[@X_KM,Y_KM]" in text and "[km]" in text


def test_version():
    for args in (("--version",), ("version",)):
        r = cli(*args)
        assert r.returncode == 0 and __version__ in r.stdout


def test_progress_lines_in_a_log(tmp_path):
    """Not a terminal (a pipe, as in a batch log): plain progress lines with the time left, no bar."""
    case = tmp_path / "c.toml"
    case.write_text(
        '[crater]\nkind = "crater"\ndiameter_km = 2.0\nfacets = 60\n[location]\nlat_deg = -85.0\n'
        '[period]\nstart = "2019-01-01"\nend = "2019-01-20"\nspinup = "fixed"\nspinup_days = 1.0\n'
        "initial_temperature_K = 100.0\n"
    )
    r = cli("run", case, "-o", tmp_path / "run.nc", CRATER_THERMAL_PROGRESS_INTERVAL_S="0", CI="1")
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("progress: ")]
    assert lines, r.stderr
    assert any(re.search(r"\d+/\d+ \(\d+ %\), .* elapsed, eta ", ln) for ln in lines), lines
    assert "\x1b[" not in r.stderr and "━" not in r.stderr  # no terminal escapes, no bar glyphs
    quiet = cli("run", case, "-o", tmp_path / "q.nc", "--quiet", CRATER_THERMAL_PROGRESS_INTERVAL_S="0.05")
    assert quiet.returncode == 0 and "progress:" not in quiet.stderr


@pytest.mark.slow
def test_sweep_worker_warnings_are_one_line(tmp_path):
    """The loose profile 800/1100 extrapolates Table 7.2: its warning, raised in a sweep worker process,
    prints as one ``warning:`` line with no source line."""
    case = tmp_path / "w.toml"
    case.write_text(
        '[crater]\nkind = "crater"\ndiameter_km = 2.0\nfacets = 40\n[location]\nlat_deg = -85.0\n'
        '[period]\nstart = "2019-01-01"\nend = "2019-01-05"\nspinup = "fixed"\nspinup_days = 1.0\n'
        'initial_temperature_K = 100.0\n[replay]\nprofiles = ["800/1100"]\n'
    )
    r = cli("sweep", case, "-o", tmp_path / "out", "--workers", "1", "--quiet")
    assert r.returncode == 0, r.stderr
    warnings_ = [ln for ln in r.stderr.splitlines() if "extrapolated" in ln]
    assert warnings_ and all(ln.startswith("warning: ") for ln in warnings_), r.stderr
    assert ".py:" not in r.stderr and "warnings.warn" not in r.stderr


def test_inverted_profile_error_names_the_option(tmp_path):
    from crater_thermal import profiles
    from crater_thermal.errors import ProfileError

    with pytest.raises(ProfileError, match="--allow-inverted"):
        profiles.parse_profile("1800/1300")
