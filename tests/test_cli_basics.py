import os
import subprocess
import sys
from pathlib import Path

import pytest

from synthetic import make_run

ENV = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}


def test_help_lists_and_exits_zero():
    out = subprocess.run([sys.executable, "-m", "crater_thermal", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    assert "crater" in out.stdout.lower()


def test_unknown_command_exits_2_without_traceback():
    out = subprocess.run([sys.executable, "-m", "crater_thermal", "no-such-command"], capture_output=True, text=True)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr


def _one_line_error(r, code, prefix="error:"):
    assert r.returncode == code, r.stderr
    assert r.stderr.startswith(prefix) and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr


def test_replay_into_an_existing_folder_exit_2(tmp_path):
    flux = tmp_path / "run.nc"
    make_run(lat_deg=-86.0, n_lunar_days=0.5, n_rings=4).to_netcdf(flux)
    (tmp_path / "results").mkdir()
    for extra in ([], ["--overwrite"]):
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "crater_thermal",
                "replay",
                str(flux),
                "--profile",
                "rock",
                "-o",
                str(tmp_path / "results"),
                *extra,
            ],
            capture_output=True,
            text=True,
            env=ENV,
        )
        _one_line_error(r, 2)
        assert "is a folder" in r.stderr
    assert list((tmp_path / "results").iterdir()) == []


def test_internal_error_exit_3_asks_for_a_bug_report(monkeypatch, capsys, tmp_path):
    from crater_thermal import cli, geometry
    from crater_thermal.errors import SolverError

    def fail(*a, **k):
        raise SolverError("conduction solver: the Newton iteration did not converge\nin column 3")

    monkeypatch.setattr(geometry, "crater_mesh", fail)
    with pytest.raises(SystemExit) as exit_:
        cli.main(["mesh", "crater", "-o", str(tmp_path / "c.ply")])
    err = capsys.readouterr().err
    assert exit_.value.code == 3 and err.count("\n") == 1
    assert err.startswith("internal error: conduction solver") and "report" in err


def test_user_errors_are_not_internal_errors():
    from crater_thermal import errors

    for cls in (
        errors.ConfigError,
        errors.MeshError,
        errors.FluxFileError,
        errors.ProfileError,
        errors.EphemerisRangeError,
        errors.OutputExistsError,
        errors.MissingExtraError,
    ):
        assert issubclass(cls, errors.CraterThermalError) and not issubclass(cls, errors.InternalError)
    assert issubclass(errors.SolverError, errors.InternalError)
    assert not issubclass(errors.SolverError, errors.CraterThermalError)
