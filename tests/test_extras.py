"""Optional extras fail cleanly where they are used: the missing module is simulated (sys.modules[name] = None,
which makes ``import name`` raise ImportError), so these run whether or not the extra is installed."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from crater_thermal import viz
from crater_thermal.errors import MissingExtraError
from crater_thermal.extras import missing_extra

from synthetic import make_run

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("extras")
    make_run(lat_deg=-86.0, n_lunar_days=0.5, n_rings=4).to_netcdf(d / "run.nc")
    return d


def test_missing_extra_message_names_the_extra():
    err = missing_extra("pyvista", "viz", "3-D views")
    assert isinstance(err, MissingExtraError)
    assert str(err) == "3-D views need pyvista, which is not installed: pip install 'crater_thermal[viz]'"


def test_show_without_pyvista_names_the_extra(files, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyvista", None)  # as if the viz extra were not installed
    with pytest.raises(MissingExtraError, match=r"pip install 'crater_thermal\[viz\]'"):
        viz.show(files / "run.nc", screenshot=tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_cli_show_without_pyvista_one_line_exit_2(files, tmp_path):
    code = (
        "import sys; sys.modules['pyvista'] = None; from crater_thermal.cli import main; "
        f"main(['show', {str(files / 'run.nc')!r}, '--screenshot', {str(tmp_path / 'x.png')!r}])"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error:") and r.stderr.count("\n") == 1, r.stderr
    assert "crater_thermal[viz]" in r.stderr
