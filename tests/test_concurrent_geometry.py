"""The view factors and the horizon map traced at the same time (``simulate.case_operator_and_horizons``):
the same operator and map as one after the other, the horizon map stopped when the view factors fail, its
progress shown when it outlasts them."""

import contextlib
import dataclasses
import functools
import threading
import time
import types

import numpy as np
import pytest

from crater_thermal import config, horizons, simulate, sunlight
from crater_thermal.errors import MeshError

CASE = """
name = "concurrent"
[crater]
kind = "crater"
diameter_km = 2.0
facets = 400
[location]
lat_deg = -85.0
lon_deg = 0.0
[period]
start = "2019-01-01"
end = "2019-01-05"
"""


@pytest.fixture()
def case(tmp_path, monkeypatch):
    monkeypatch.setenv("CRATER_THERMAL_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "case.toml"
    path.write_text(CASE)
    return config.load_case(path)


def _horizon_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("horizons")]


def test_together_equal_one_after_the_other(case, tmp_path, monkeypatch):
    timer = simulate.Timer()
    mesh, tracer = simulate.case_scene(case, timer)
    F, hmap = simulate.case_operator_and_horizons(case, mesh, tracer, timer)
    assert list((tmp_path / "cache").rglob("*.npz")), "the map traced on the thread is cached as before"
    # the sequential reference, with a cold cache of its own
    monkeypatch.setenv("CRATER_THERMAL_CACHE", str(tmp_path / "cache_ref"))
    F_ref = simulate.case_operator(case, mesh, tracer, simulate.Timer())
    ref = sunlight.Sunlight(case.sun, case.surface, case.scattering, mesh, tracer, F_ref)
    np.testing.assert_array_equal(hmap.elevation, ref.hmap.elevation)
    x = np.linspace(1.0, 2.0, mesh.n_facets)
    np.testing.assert_array_equal(F @ x, F_ref @ x)
    assert {"viewfactors", "horizons"} <= set(timer.split)
    # the map handed to Sunlight is used as it is (not traced again)
    light = simulate.case_sunlight(case, mesh, tracer, F, hmap=hmap)
    assert light.hmap is hmap
    assert not _horizon_threads()


def test_rays_method_and_resumed_sunlight_trace_no_map(case):
    mesh, tracer = simulate.case_scene(case, simulate.Timer())
    assert simulate.case_operator_and_horizons(case, mesh, tracer, simulate.Timer(), horizons=False)[1] is None
    rays = dataclasses.replace(case, sun=dataclasses.replace(case.sun, method="rays"))
    assert simulate.case_operator_and_horizons(rays, mesh, tracer, simulate.Timer())[1] is None


def test_a_map_of_another_mesh_is_refused(case):
    mesh, tracer = simulate.case_scene(case, simulate.Timer())
    other = horizons.HorizonMap(np.zeros((8, mesh.n_facets), np.float32), "not-this-mesh", 0.1, 0.0)
    with pytest.raises(MeshError, match="different mesh"):
        sunlight.Sunlight(case.sun, case.surface, case.scattering, mesh, tracer, None, hmap=other)


def test_a_failed_operator_stops_the_horizon_map(case, tmp_path, monkeypatch):
    """The view factors fail early; the horizon map (slowed to batches of 0.2 s) stops at its next batch,
    caches nothing, and the operator's error is the one raised."""
    mesh, tracer = simulate.case_scene(case, simulate.Timer())
    batches = []
    real = horizons._trace_hierarchical

    def slow(*args, **kw):
        batches.append(time.monotonic())
        time.sleep(0.2)
        return real(*args, **kw)

    monkeypatch.setattr(horizons, "_trace_hierarchical", slow)
    # 10 facets per batch: 40 batches, ~8 s in all
    monkeypatch.setattr(horizons, "horizon_map", functools.partial(horizons.horizon_map, chunk_rays=720 * 10))

    def failing_build(*args, **kw):
        time.sleep(0.3)
        raise RuntimeError("view factors failed")

    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="view factors failed"):
        simulate.case_operator_and_horizons(case, mesh, tracer, simulate.Timer(), build=failing_build)
    assert time.monotonic() - t0 < 2.0, "the horizon map was not stopped"
    assert 1 <= len(batches) <= 4
    assert not _horizon_threads()
    assert not list((tmp_path / "cache").rglob("*.npz")), "a stopped horizon map must not be cached"


def test_a_horizon_map_outlasting_the_operator_gets_its_own_progress_stage(case, monkeypatch):
    mesh, tracer = simulate.case_scene(case, simulate.Timer())
    real = horizons._trace_hierarchical

    def slow(*args, **kw):
        time.sleep(0.05)
        return real(*args, **kw)

    monkeypatch.setattr(horizons, "_trace_hierarchical", slow)
    # 10 batches, >= 0.5 s
    monkeypatch.setattr(horizons, "horizon_map", functools.partial(horizons.horizon_map, chunk_rays=720 * 40))
    stages, calls = [], []

    @contextlib.contextmanager
    def reporter(description):
        stages.append(description)
        yield lambda done, total: calls.append((description, done, total))

    quick = lambda *a, **k: types.SimpleNamespace(is_zero=True)  # noqa: E731 - an operator built at once
    F, hmap = simulate.case_operator_and_horizons(case, mesh, tracer, simulate.Timer(), progress=reporter, build=quick)
    assert F is None and hmap.elevation.shape[1] == mesh.n_facets
    assert stages[-1] == f"horizon map ({mesh.n_facets} facets)"
    mine = [c for c in calls if c[0] == stages[-1]]
    assert mine and mine[-1][1:] == (mesh.n_facets, mesh.n_facets)
    assert not _horizon_threads()


def test_a_cached_map_is_read_on_the_calling_thread(case, monkeypatch):
    """numpy parses an .npz header with ast.literal_eval, which CPython 3.11.7 fails on when two threads
    parse at once (gh-106905; it broke CI at df264f7): a cached horizon map is read before any thread is
    started, and the thread, when one traces, never reads the cache."""
    mesh, tracer = simulate.case_scene(case, simulate.Timer())
    first = simulate.case_operator_and_horizons(case, mesh, tracer, simulate.Timer())[1]
    readers = []
    real_load = horizons._load
    monkeypatch.setattr(horizons, "_load", lambda *a: readers.append(threading.current_thread().name) or real_load(*a))
    started = []
    real_submit = simulate.ThreadPoolExecutor.submit
    monkeypatch.setattr(
        simulate.ThreadPoolExecutor, "submit", lambda *a, **k: started.append(1) or real_submit(*a, **k)
    )
    again = simulate.case_operator_and_horizons(case, mesh, tracer, simulate.Timer())[1]
    np.testing.assert_array_equal(again.elevation, first.elevation)
    assert readers == [threading.main_thread().name] and not started
    # with the cache emptied the map is traced on the thread, which does not look in the cache
    for f in simulate.cache.folder("horizons").glob("*.npz"):
        f.unlink()
    readers.clear()
    traced = simulate.case_operator_and_horizons(case, mesh, tracer, simulate.Timer())[1]
    np.testing.assert_array_equal(traced.elevation, first.elevation)
    assert started and all(name == threading.main_thread().name for name in readers)


def test_no_module_but_io_calls_numpy_load():
    """Every .npy/.npz read goes through io.load_npy / io.load_npz (their header parsing under one lock)."""
    import pathlib

    import crater_thermal

    root = pathlib.Path(crater_thermal.__file__).parent
    offenders = [
        str(p.relative_to(root)) for p in root.rglob("*.py") if p.name != "io.py" and "np.load(" in p.read_text()
    ]
    assert not offenders, offenders
