"""The one progress contract: computations call ``progress(done, total)``; only crater_thermal.progress draws."""

import ast
from pathlib import Path

import numpy as np
import xarray as xr

from crater_thermal import progress, simulate, thermal

PACKAGE = Path(__file__).resolve().parents[1] / "crater_thermal"


def test_enabled_flag_wins_quiet_env_silences_ci_gets_lines(monkeypatch):
    monkeypatch.delenv("CRATER_THERMAL_QUIET", raising=False)
    monkeypatch.setenv("CI", "1")
    assert progress.enabled(None) is True  # a CI log gets progress lines, not silence
    assert progress._on_terminal() is False  # ... as lines, never a bar
    monkeypatch.setenv("CRATER_THERMAL_QUIET", "1")
    assert progress.enabled(None) is False
    assert progress.enabled(True) is True
    monkeypatch.delenv("CI")
    monkeypatch.delenv("CRATER_THERMAL_QUIET")
    assert progress.enabled(False) is False


def test_line_progress_at_most_one_line_per_interval_with_eta():
    """100 work units, one per second of a fake clock, lines at most every 30 s: 3 lines and a closing one."""
    import io as stdio

    now = [0.0]
    out = stdio.StringIO()
    lines = progress.LineProgress("record", 30.0, clock=lambda: now[0], stream=out)
    for k in range(1, 101):
        now[0] = float(k)
        lines(k, 100)
    lines.close()
    text = out.getvalue().splitlines()
    assert text[:3] == [
        "progress: record: 30/100 (30 %), 30 s elapsed, eta 1 min 10 s",
        "progress: record: 60/100 (60 %), 1 min 0 s elapsed, eta 40 s",
        "progress: record: 90/100 (90 %), 1 min 30 s elapsed, eta 10 s",
    ]
    assert text[3:] == ["progress: record: done in 1 min 40 s"]
    quiet = stdio.StringIO()  # a stage shorter than the interval prints nothing at all
    short = progress.LineProgress("short", 30.0, clock=lambda: 0.0, stream=quiet)
    short(1, 1)
    short.close()
    assert quiet.getvalue() == ""


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
