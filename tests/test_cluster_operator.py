"""The view-factor operator of a run on a dask cluster, built by the workers that hold its rows (issue 22
item 2: "the operator's blocks held by the workers that own their rows").

References: the whole compressed operator built in one process (:func:`vfoperator.compressed_view_factors`),
whose products the workers' row blocks must give to round-off, through a real scheduler and two worker
processes started with dask's own command line on 127.0.0.1."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from crater_thermal import cluster_run, geometry, io, radiosity, vfoperator

distributed = pytest.importorskip("distributed")

import dask_procs  # noqa: E402

# the row blocks apply the same stored entries as the whole operator, summed in another order (the
# operator's float32 factors in float64 products): round-off of the largest product, ~1e-15; 1e-12 leaves
# a margin of 1000 and still fails for one missing or doubled entry (>= 1e-6 of the largest here)
ROUNDOFF = 1e-12


def _close(got, ref):
    np.testing.assert_allclose(got, ref, rtol=0, atol=ROUNDOFF * np.abs(ref).max())


# several right-hand sides are multiplied in float32 arithmetic by both (vfoperator.PRODUCT_DTYPE), summed in
# other orders: float32 rounding of sums of ~100 terms, a few 1e-7 of the largest; 2e-6 is a margin of ~10
FLOAT32_ROUNDOFF = 2e-6


def _close32(got, ref):
    np.testing.assert_allclose(got, ref, rtol=0, atol=FLOAT32_ROUNDOFF * np.abs(ref).max())


def test_operator_built_on_the_workers_equals_the_whole_one(tmp_path, monkeypatch):
    """An inward sphere of 800 facets (every facet sees most others; row sums above 1, so the rescale of
    all row sums applies) in 3 chunks on 2 workers: ``F x``, ``F X`` and ``F^T y`` from the workers' rows
    equal the whole operator's; this process holds only the facet order and areas. Then one worker is
    SIGKILLed (and its nanny: a lost machine): its rows are made again on the other (built again, or
    rescaled again from unscaled rows still held there, seen in the scheduler's task stream) and the
    products are unchanged."""
    mesh = geometry.sphere_mesh(800)
    whole = vfoperator.compressed_view_factors(mesh)
    assert whole.scale is not None and whole.stats["lowrank_blocks"] > 0  # the rescale and far blocks
    rng = np.random.default_rng(3)
    x, X, y = rng.random(mesh.n_facets), rng.random((mesh.n_facets, 4)), rng.random(mesh.n_facets)
    store = io.SegmentStore(tmp_path / "run.nc.partial", 8)
    with dask_procs.cli_cluster(tmp_path, 2) as (address, workers):
        factory = cluster_run.distributed_columns(scheduler=address, chunk_facets=300)
        with factory(None, mesh, store) as session:
            F = session.view_factors(mesh, None, "compressed", vfoperator.DEFAULT_TOLERANCE)
            assert isinstance(F, cluster_run.ClusterOperator) and len(F.rows) == 3
            assert np.array_equal(np.sort(F.order), np.arange(mesh.n_facets))  # every row in one chunk
            # one right-hand side in float64 (every stored entry to round-off), several in float32
            _close(F @ x, whole @ x)
            _close32(F @ X, whole @ X)
            _close(F.rmatvec(y), whole.rmatvec(y))
            assert F.rowsum_excess == pytest.approx(whole.rowsum_excess, abs=1e-12) and not F.is_zero
            # the whole operator's entries are on the workers, not here
            assert F.nbytes == 16 * mesh.n_facets and F.held_bytes >= whole.nbytes // 2
            monkeypatch.setattr(radiosity, "ITERATIVE_BLOCK", 1)  # 4 lit blocks: ASYNC_SOLVES in flight
            E, Q = _scattering_through_the_workers(F, whole, rng)
            client = session.client
            victim = dask_procs.process_of(client, _sole_holder(client, F.rows), workers)
            with distributed.get_task_stream(client) as stream:
                os.killpg(victim.pid, signal.SIGKILL)
                t0 = time.monotonic()
                while len(client.scheduler_info()["workers"]) > 1:
                    assert time.monotonic() - t0 < 60, "the scheduler did not notice the lost worker"
                    time.sleep(0.05)
                _close(F @ x, whole @ x)
                _close32(F @ X, whole @ X)
                # the scattered sunlight's products through the one worker left: the same numbers
                assert np.array_equal(radiosity.ScatteringSolver(F, 0.3, solver="iterative").solar_incident(E), Q)
            # the lost block made again: rescaled from its unscaled rows where these were still held on the
            # other worker ("ct-rows-"), else built again from the mesh ("ct-build-"): which one depends on
            # when dask released the unscaled rows, a race the test must not depend on
            keys = [str(t["key"]) for t in stream.data]
            rebuilt = [k for k in keys if k.startswith(("ct-build-", "ct-rows-"))]
            assert rebuilt, f"no row block was made again: the test proves nothing (tasks run: {sorted(set(keys))})"


def _sole_holder(client, futures, timeout_s=60.0):
    """The address of a worker that alone holds one of ``futures``: killing it loses that block, so it must
    be made again. The products copy blocks between the workers; dask's active memory manager (its
    ReduceReplicas policy, on by default) drops the copies no task waits for, here asked to run now
    instead of at its next 2-s pass."""
    t0 = time.monotonic()
    while True:
        sole = sorted(addrs[0] for addrs in client.who_has(futures).values() if len(addrs) == 1)
        if sole:
            return sole[0]
        assert time.monotonic() - t0 < timeout_s, "every row block is still held by both workers"
        client.amm.run_once()
        time.sleep(0.2)


def _scattering_through_the_workers(F, whole, rng):
    """The scattered sunlight's fixed points with the workers' products (several solves in flight: the
    operator is asynchronous) against the whole operator's solve in one process: to the products'
    round-off carried through the fixed point (1 / (1 - q), q = A max row sum <= 0.3) plus both solves'
    stopping rules (ITERATIVE_RTOL of the largest first bounce, / (1 - q) each); several samples, one
    dark, and one sample alone (float64 products). Returns the samples and their incident light."""
    nf = F.shape[0]
    E = rng.uniform(0.0, 1000.0, (5, nf)) * (rng.random((5, nf)) < 0.6)
    E[3] = 0.0  # a dark sample: skipped
    assert F.asynchronous
    cluster = radiosity.ScatteringSolver(F, 0.3, solver="iterative")
    local = radiosity.ScatteringSolver(whole, 0.3, solver="iterative")
    for e in (E, E[0]):
        Q, ref = cluster.solar_incident(e), local.solar_incident(e)
        stopping = 2 * radiosity.ITERATIVE_RTOL * 0.3 * np.abs(e).max() / 0.7
        np.testing.assert_allclose(Q, ref, rtol=0, atol=FLOAT32_ROUNDOFF * np.abs(ref - e).max() / 0.7 + stopping)
    assert np.array_equal(cluster.solar_incident(E)[3], E[3])  # the dark sample: skipped, no light
    return E, cluster.solar_incident(E)


def test_rows_of_another_mesh_are_refused(tmp_path):
    """A worker builds rows only from the run's own mesh: mesh files that another run left or changed in
    the scratch folder (another hash than the run's) stop the task with one line, and a plan cached on the
    worker for another mesh at the same path is not reused."""
    from crater_thermal.errors import ConfigError

    a, b = geometry.sphere_mesh(200), geometry.sphere_mesh(202)
    folder = tmp_path / "mesh"
    folder.mkdir()
    settings = {"tolerance": vfoperator.DEFAULT_TOLERANCE, "tolerance_mode": "block"}
    for mesh in (a, b):  # the same folder, a new mesh: built from the new one, not the cached plan
        np.save(folder / "vertices.npy", mesh.vertices)
        np.save(folder / "faces.npy", mesh.faces)
        block = cluster_run.build_rows(str(folder), 0, mesh.n_facets, {**settings, "mesh_hash": mesh.hash})
        assert block.n == mesh.n_facets
    with pytest.raises(ConfigError, match="is not the run's"):
        cluster_run.build_rows(str(folder), 0, 10, {**settings, "mesh_hash": a.hash})
