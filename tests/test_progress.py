"""The one progress contract: computations call ``progress(done, total)``; only crater_thermal.progress draws."""

import ast
from pathlib import Path

import numpy as np
import xarray as xr

from crater_thermal import progress, simulate, thermal

PACKAGE = Path(__file__).resolve().parents[1] / "crater_thermal"


def test_enabled_flag_wins_and_ci_is_quiet(monkeypatch):
    monkeypatch.setenv("CI", "1")
    assert progress.enabled(None) is False
    assert progress.enabled(True) is True
    monkeypatch.delenv("CI")
    monkeypatch.delenv("CRATER_THERMAL_QUIET", raising=False)
    assert progress.enabled(False) is False


def test_bar_and_reporter():
    with progress.bar("quiet", False) as cb:
        assert cb is None
    assert progress.reporter(False) is None
    with progress.reporter(True)("stage") as cb:  # draws on stderr (captured here): must not fail
        for k in range(1, 4):
            cb(k, 3)


def test_replay_reports_profiles_done():
    t = np.datetime64("2019-01-01") + np.arange(6) * np.timedelta64(4, "h")
    s = np.full((6, 2), 50.0)
    ds = xr.Dataset(
        {"solar_incident": (("time", "facet"), s), "ir_incident": (("time", "facet"), s / 10)},
        coords={"time": t},
        attrs={"albedo": 0.12, "emissivity": 0.98},
    )
    profiles = [thermal.parse_profile(x) for x in ("1300/1800", "1500/1800", "rock")]
    calls = []
    simulate.replay_fluxes(
        ds,
        profiles,
        initial_temperature=100.0,
        chunk_columns=2,
        progress=lambda done, total: calls.append((done, total)),
    )
    # one profile per chunk of 2 columns (2 facets); progress in time steps of the chunks: 3 x 5 steps
    assert calls == [(5, 15), (10, 15), (15, 15)]


def test_only_the_progress_module_imports_rich():
    importers = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            if any(n == "rich" or n.startswith("rich.") for n in names):
                importers.append(path.name)
    assert set(importers) == {"progress.py"}
