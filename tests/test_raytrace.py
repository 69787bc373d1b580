"""Tests for crater_thermal.raytrace (Embree occlusion / first-hit queries)."""

import math

import numpy as np
import pytest

from crater_thermal.errors import MeshError
from crater_thermal.geometry import Mesh, crater_mesh, flat_mesh, sphere_mesh
from crater_thermal.raytrace import MIN_OFFSET_ULPS, RAY_OFFSET_FRACTION, RayTracer


@pytest.fixture(scope="module")
def crater():
    return crater_mesh(10.0, 2000)


def test_offset_constant_and_origins(crater):
    rt = RayTracer(crater)
    assert 0 < RAY_OFFSET_FRACTION < 0.01
    idx = np.array([0, 5, 1999])
    o = rt.facet_origins(idx)
    lift = np.einsum("ij,ij->i", o - crater.centroids[idx], crater.normals[idx])
    expected = np.maximum(RAY_OFFSET_FRACTION * crater.facet_size[idx], rt.min_offset)
    assert np.allclose(lift, expected, rtol=1e-9)
    # off-normal displacement is zero: the origin is straight above the centroid
    assert np.allclose(o - crater.centroids[idx], lift[:, None] * crater.normals[idx], atol=1e-9)
    with pytest.raises(MeshError, match="out of range"):
        rt.facet_origins([2000])


def test_rays_from_sphere_centre_hit_everything():
    m = sphere_mesh(500, radius_m=3.0)
    rt = RayTracer(m)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(4000, 3))
    o = np.zeros_like(d)
    hit = rt.first_hit(o, d)
    assert hit.dtype == np.int64 and np.all(hit >= 0)
    assert np.all(rt.occluded(o, d))
    # the hit facet's plane is crossed in the ray direction: its normal (inward) opposes the ray
    assert np.all(np.einsum("ij,ij->i", m.normals[hit], d) < 0)
    # tfar shorter than the inscribed radius (R cos(max edge angle) > 2.9): nothing is hit
    assert not rt.occluded(o, d / np.linalg.norm(d, axis=1)[:, None], tfar=2.5).any()
    assert np.all(rt.first_hit(o, d / np.linalg.norm(d, axis=1)[:, None], tfar=2.5) == -1)
    # per-ray tfar
    t = np.where(np.arange(4000) % 2 == 0, 2.5, 3.5)
    occ = rt.occluded(o, d / np.linalg.norm(d, axis=1)[:, None], tfar=t)
    assert np.array_equal(occ, np.arange(4000) % 2 == 1)


def test_no_self_hits_from_offset_origins(crater):
    rt = RayTracer(crater)
    rng = np.random.default_rng(2)
    nf = crater.n_facets
    idx = np.repeat(np.arange(nf), 8)
    # random directions in each facet's upper hemisphere
    d = rng.normal(size=(idx.size, 3))
    n = crater.normals[idx]
    d = np.where((np.einsum("ij,ij->i", d, n) < 0)[:, None], -d, d)
    hit = rt.first_hit(rt.facet_origins(idx), d)
    assert not np.any(hit == idx)


def test_crater_floor_sky_and_horizon(crater):
    rt = RayTracer(crater)
    z = crater.centroids[:, 2]
    floor = np.flatnonzero(z < z.min() + 1.0)
    o = rt.facet_origins(floor)
    up = np.tile([0.0, 0.0, 1.0], (floor.size, 1))
    assert not rt.occluded(o, up).any()
    # the wall rises about 50 deg above the floor centre as seen from there: a 10 deg-elevation ray
    # is blocked, whatever its azimuth
    az = np.linspace(0, 2 * math.pi, floor.size, endpoint=False)
    el = math.radians(10.0)
    low = np.stack([np.cos(az) * math.cos(el), np.sin(az) * math.cos(el), np.full(floor.size, math.sin(el))], 1)
    assert rt.occluded(o, low).all()
    assert np.all(rt.first_hit(o, low) >= 0)


def test_threads_agree_and_large_batches(crater):
    rng = np.random.default_rng(3)
    n = 200_000  # several chunks
    idx = rng.integers(0, crater.n_facets, n)
    d = rng.normal(size=(n, 3))
    r1 = RayTracer(crater, n_threads=1)
    r2 = RayTracer(crater, n_threads=4)
    o = r1.facet_origins(idx)
    assert np.array_equal(r1.occluded(o, d), r2.occluded(o, d))
    assert np.array_equal(r1.first_hit(o, d), r2.first_hit(o, d))


def test_far_from_origin_uses_centre_relative_float32():
    # a crater placed 1000 km from the frame origin: float32 absolute coordinates would have 6 cm
    # spacing there; centre-relative ones keep the same answers as the untranslated mesh
    base = crater_mesh(10.0, 502)
    shift = np.array([1.0e6, -2.0e6, 5.0e5])
    far = Mesh(base.vertices + shift, base.faces, base.meta)
    ra, rb = RayTracer(base), RayTracer(far)
    rng = np.random.default_rng(4)
    idx = rng.integers(0, 502, 20000)
    d = rng.normal(size=(20000, 3))
    assert np.array_equal(ra.first_hit(ra.facet_origins(idx), d), rb.first_hit(rb.facet_origins(idx), d))


def test_bad_shapes():
    rt = RayTracer(flat_mesh(1.0, 2))
    with pytest.raises(MeshError, match="shape"):
        rt.occluded(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(MeshError, match="shape"):
        rt.first_hit(np.zeros(3), np.zeros(3))
    with pytest.raises(MeshError):
        RayTracer("not a mesh")
    assert rt.occluded(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_min_offset_floor():
    # a mesh of very small facets far apart: the float32 floor applies
    m = flat_mesh(1.0, 2)
    rt = RayTracer(m)
    assert rt.min_offset == pytest.approx(MIN_OFFSET_ULPS * np.finfo(np.float32).eps * 0.5)
    assert np.all(rt.offsets >= rt.min_offset)


def _tracing_threads() -> list:
    import threading

    return [t for t in threading.enumerate() if t.name.startswith("raytrace")]


def test_batches_reuse_one_pool_of_threads(crater):
    """Many multi-chunk batches are traced by the same n threads (no threads started per batch), with the
    same answers as one thread tracing the whole batch."""
    rng = np.random.default_rng(5)
    n = 3 * 2048  # several chunks of the 2-thread split
    idx = rng.integers(0, crater.n_facets, n)
    d = rng.normal(size=(n, 3))
    r1 = RayTracer(crater, n_threads=1)
    r2 = RayTracer(crater, n_threads=2)
    o = r1.facet_origins(idx)
    ref = r1.occluded(o, d)
    assert np.array_equal(r2.occluded(o, d), ref)
    threads = {t.ident for t in _tracing_threads()}
    assert threads  # the batch was split over the pool's threads
    for _ in range(20):
        assert np.array_equal(r2.occluded(o, d), ref)
    assert {t.ident for t in _tracing_threads()} == threads


def test_a_forked_child_traces_with_its_own_pool(crater):
    """The pool is per process: a child forked after the parent traced (its pool's threads do not exist
    in the child) still traces, with the parent's answers."""
    import multiprocessing

    rng = np.random.default_rng(6)
    n = 4 * 2048
    idx = rng.integers(0, crater.n_facets, n)
    d = rng.normal(size=(n, 3))
    rt = RayTracer(crater, n_threads=2)
    o = rt.facet_origins(idx)
    ref = rt.occluded(o, d)  # the parent's pool now exists

    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=lambda: queue.put(rt.occluded(o, d)))  # forked: nothing pickled but the answer
    child.start()
    try:
        got = queue.get(timeout=60)
    finally:
        child.join(timeout=30)
        if child.is_alive():
            child.kill()
    assert np.array_equal(got, ref)
