"""A coupled run on a dask.distributed cluster: the facet columns spread over workers, coupled through the
radiation operator by waveform relaxation (:mod:`crater_thermal.waveform`).

The facets are cut into chunks of contiguous rows of the operator's own order (the compressed
operator's cluster order: spatial neighbours together): by default one chunk per worker present at the
start, or at most ``--chunk-facets`` each and at least one per worker. The cluster is connected once the
mesh is made (:func:`distributed_columns` yields a session to :func:`crater_thermal.runner.run_case`)
and the view-factor operator is built by the workers that hold its rows:

* **compressed operator**: the mesh is saved into the run's scratch store (``OUT.partial/mesh/``) and
  each chunk's rows are built by a worker from it, as a dask task (:func:`build_rows`,
  :meth:`crater_thermal.vfoperator.CompressedPlan.row_block`: the same tree and partition as the whole
  operator, deterministic from the mesh, and only the blocks that meet the chunk's rows; a block that
  meets two chunks is built by both). The rescale that keeps row sums <= 1 needs every row's sum: each
  chunk's row sums (n floats in all) go to one task that makes the scale vector, and each chunk's rows
  take it (:func:`_scaled`). The client keeps the row sums' and the scale's futures, so a lost worker's
  rows are built again elsewhere from the mesh. The client holds no part of the operator: its products
  (the scattered sunlight, the start's IR) go through a :class:`ClusterOperator` that sends the operand
  once and gathers each chunk's rows of the product;
* **exact matrix** (small by construction: below ``vfoperator.AUTO_COMPRESSED_MIN_FACETS`` facets, or
  asked for): built by the client as a local run builds it, written into ``OUT.partial/operator/`` and
  loaded row block by row block by the workers (:func:`crater_thermal.vfoperator.load_row_block`).

Either way each worker holds only its chunks' rows, and the scratch store must be on a filesystem every
worker reads at the same path. The sunlight (direct and scattered) goes into the store as in a local run.

Then the time loop, window by window (the recorded period in windows of
:func:`crater_thermal.waveform.window_samples` samples, the spin-up window in blocks). A record window
(:meth:`DaskColumns.relax_window`): the client sends each chunk's start state and sunlight (float32
where that is exact: :func:`_compact`) and the start's emission (one row); each task forms its rows' IR
from every chunk's emission (fetched worker to worker, in the products' type) and its rows of the
operator, and conducts its columns through the window on one thread; each chunk forms its next emission
and its largest change where it is, and only that number comes back per iteration (the next iteration
is submitted ahead and does nothing once the window has converged). The converged window's
temperatures, IR and end states come back once. The periodic start's passes run whole on the workers
(:meth:`DaskColumns.held_pass`, :meth:`DaskColumns.lagged_pass`). The client keeps the state, writes the
rows into the store and the checkpoints (``--resume`` works as for a local run), and at the end writes
``run.nc`` as a local run does.

Tasks are pure functions of their inputs: a task whose worker dies is run again by the scheduler
(``retries`` for errors it raises), and an iteration (or a product) whose operand was lost with a worker
is sent again.

Equal to the single-process run with ``[steps] ir_coupling = "relaxed"`` within the relaxation tolerance
(the chunks converge on the same fixed point; tested to 0.01 K); against the default extrapolated scheme
the difference is that scheme's coupling error (``docs/model.md``).

dask is imported only inside :func:`distributed_columns`'s context."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from crater_thermal import cluster, geometry, io, radiosity, raytrace, runner, vfoperator, waveform
from crater_thermal.errors import ConfigError, CraterThermalError, InternalError

#: Times dask re-runs a task that raised before the run stops.
RETRIES = 3
#: Times an iteration is sent again after its inputs were lost with a worker.
RESENDS = 3
#: Seconds to wait for a worker (a restarted one, a new one) before a run with none left stops [s];
#: the environment variable ``CRATER_THERMAL_WORKER_WAIT_S`` sets another.
WORKER_WAIT_S = 30.0


def worker_wait_s() -> float:
    """How long a run with no worker left waits for one [s] (``CRATER_THERMAL_WORKER_WAIT_S``, default
    :data:`WORKER_WAIT_S`)."""
    try:
        return max(0.0, float(os.environ.get("CRATER_THERMAL_WORKER_WAIT_S", WORKER_WAIT_S)))
    except ValueError:
        return WORKER_WAIT_S


_SOLVERS = threading.local()  # per worker thread: a column solver per (options, columns), reused across tasks
_PLANS: dict = {}  # per worker process: the compressed plan of the latest mesh, while its rows are built
# a worker with several threads: one of them builds the plan while the others wait for it (without the
# lock each would build its own: right, but the plan's rays traced once per thread)
_PLANS_LOCK = threading.Lock()


def _solver(options: dict, n: int):
    """A column solver of ``n`` columns with ``options``, kept for the next task of this worker thread (a
    solver holds its columns' state while it runs: two tasks running at once on a worker of several
    threads must not share one)."""
    key = (json.dumps(options, sort_keys=True), n)
    solvers = _SOLVERS.__dict__.setdefault("by_key", {})
    s = solvers.get(key)
    if s is None:
        solvers.clear()  # one chunk size at a time: the last chunk may be shorter
        s = solvers[key] = runner.column_solver(options["profile"], n, options)
    return s


def load_rows(folder: str, a: int, b: int):
    """A worker's rows ``a:b`` of the saved operator (None when the run has no exchange). A dask task."""
    return None if folder is None else vfoperator.load_row_block(folder, a, b)


def solve_chunk(
    rows, facets, E, state, times_s, solar, ir0, options: dict, prev=None, skip_K: float = 0.0, hold: bool = False
):
    """Conduct one chunk's columns through a window (runs on a worker, one thread).

    Parameters
    ----------
    rows : the chunk's :class:`vfoperator.RowBlock` (None: no exchange).
    facets : (m,) its facet indices; E : (n, nf) emitted flux of every facet [W m-2];
    state : (m, nz) [K]; times_s : (n,) [s]; solar : (n, m) [W m-2]; ir0 : (m,) IR at sample 0 or None.
    options : the columns' profile, property set, emissivity, geothermal flux, sub-step, albedo.
    prev, skip_K : this chunk's result of the previous iteration of the window (a
        :class:`waveform.Window`, kept on the workers) and the change [K] below which a column keeps it
        (:func:`waveform.active_columns`).
    hold : ``E`` is one row (1, nf) whose IR is held over the window, conducted with the first pass's
        coarse steps (:meth:`waveform.LocalColumns.solve`).

    Returns
    -------
    waveform.Window of the chunk's columns.
    """
    with cluster.one_numba_thread():
        return _chunk_window(rows, E, len(facets), ir0, state, times_s, solar, options, prev, skip_K, hold)


def solve_chunk_parts(
    rows, facets, E, state, times_s, solar, ir0, options, prev=None, skip_K=0.0, hold=False, chunks=None, stop=None
):
    """:func:`solve_chunk` with the emitted flux of every facet given whole (``E`` (n, nf)) or as the chunks'
    parts (a list of (n, m_c) in the order of ``chunks``, a :class:`_Facets`: the previous iteration's
    :func:`_emission` of each chunk, fetched from the workers that hold them). ``stop``: (every chunk's
    largest change [K] in the previous iteration, the tolerance [K]): when none is above the tolerance the
    window has converged and this iteration is not made (returns None)."""
    if stop is not None and max(stop[0]) <= stop[1]:
        return None
    if isinstance(E, _Broadcast):
        E = E.array()
    if isinstance(E, (list, tuple)):
        E = _joined_columns(E, chunks)
    return solve_chunk(rows, facets, E, state, times_s, solar, ir0, options, prev, skip_K, hold)


def _joined_columns(parts, chunks) -> np.ndarray:
    """The chunks' column blocks ``parts`` (each (n, m_c), in the order of ``chunks``, a :class:`_Facets`)
    as one (n, nf) array of every facet, in their type. Laid out facet by facet (the transpose of a
    C-contiguous (nf, n) array): each chunk's facets are copied in as whole rows, and the operator's rows
    (:meth:`vfoperator.RowBlock.apply`, given ``E.T``) gather whole rows of it; against an (n, nf) array
    that is 2.2x faster for both at n = 96 samples and 30,000 facets in 8 chunks, 1.9x at n = 24."""
    whole = np.empty((sum(len(idx) for idx in chunks.idx), len(parts[0])), parts[0].dtype)
    for idx, part in zip(chunks.idx, parts):
        whole[idx] = part.T
    return whole.T


def _emission(w, emissivity: float) -> np.ndarray:
    """A chunk window's emitted flux [W m-2] (n, m), in the type the products take it in (:func:`_operand`)."""
    return _operand(radiosity.emitted(np.asarray(w.T, float), emissivity), len(w.T))


def _change(w, prev) -> float:
    """The largest change of a chunk's surface temperatures [K] between two iterations of a window."""
    return float(np.max(np.abs(w.T - prev.T))) if w.T.size else 0.0


def _chunk_window(
    rows, E, m: int, ir0, state, times_s, solar, options: dict, prev=None, skip_K: float = 0.0, hold: bool = False
):
    """A chunk of ``m`` columns through a window, driven by the IR its operator rows form from the emitted
    flux ``E`` (n, nf) [W m-2] of every facet (``ir0`` [W m-2] at sample 0 when given; with ``hold``, ``E``
    is one row whose IR is held over the window); the :class:`waveform.Window` of the chunk."""
    _PLANS.clear()  # the operator's rows are built: its plan is no longer needed on this worker
    solar = np.asarray(solar, np.float64)  # sent in float32 where that held it exactly (:func:`_compact`)
    ir = np.zeros((len(E), m)) if rows is None else np.maximum(rows.apply(E.T).T, 0.0)
    ir = waveform.held_ir(ir, len(times_s), hold)
    if ir0 is not None and not hold:
        ir[0] = ir0
    eps = options["emissivity"]
    a = radiosity.absorbed_flux(solar, ir, options["albedo"], eps, options["solar_is_absorbed"])
    with waveform.first_pass_steps(_solver(options, m), hold) as solver:  # a hold: the first pass's steps
        return waveform.conduct(solver, state, times_s, a, ir, prev, skip_K, eps)


#: What a run's errors on the cluster add once its record has begun (there is a checkpoint to resume from).
_RESUME = "; the checkpoint beside the output keeps the finished part: run again with --resume"


def _gave_up(exc, hint: str = "") -> ConfigError:
    """The one-line error for dask's ``KilledWorker`` (a task whose workers kept dying)."""
    return ConfigError(
        f"dask gave up a task of the run: the workers that ran it died ({exc.args[0] if exc.args else ''}; "
        f"out of memory? see their logs); smaller --chunk-facets need less memory per worker{hint}"
    )


def _failed(exc, hint: str = "") -> ConfigError:
    """The one-line error for a cluster that lost the run's data and has no worker left."""
    reason = " ".join(str(exc).split())[:160] or type(exc).__name__
    return ConfigError(f"the dask cluster failed the run ({reason}); are any workers left? (see their logs){hint}")


def _resending(client, attempt, hint: str = "", forget=None):
    """``attempt()``, sent again (up to :data:`RESENDS` times) when it fails because an input was lost
    with the worker that held it (``forget()`` first: what the next attempt must send again). An error
    raised by a task itself (:class:`CraterThermalError`, :class:`InternalError` such as a solver's or a
    relaxation that did not converge, MemoryError) is not a lost input and goes on as it is; dask's
    ``KilledWorker`` and a cluster with no worker left become one-line errors (``hint`` appended)."""
    from distributed import KilledWorker

    for n in range(RESENDS + 1):
        try:
            return attempt()
        except KilledWorker as exc:
            raise _gave_up(exc, hint) from None
        except (CraterThermalError, InternalError, MemoryError):
            raise
        except Exception as exc:
            if n == RESENDS or not _workers_left(client):
                raise _failed(exc, hint) from None
            if forget is not None:
                forget()


class DaskColumns:
    """The waveform-relaxation backend (``solve`` as :meth:`waveform.LocalColumns.solve`) on a dask cluster."""

    def __init__(self, client, chunks, row_futures, options, n_facets: int, n_workers: int):
        self.client, self.chunks, self.row_futures, self.options = client, chunks, row_futures, options
        self._n = int(n_facets)
        self._last = None  # the chunks' result futures of the latest round (the next iteration's prev)
        self._state = None  # the chunks' start states of the current window (futures)
        # lagged spin-up passes kept on the workers: sunlight per block, the latest pass's windows
        self._spin = self._pass = self._surfaces = self._chunks_f = self._next = None
        self._ahead = None  # the next inputs' tasks submitted at a pass's end (:meth:`_next_tasks`)
        self.description = f"dask: {len(chunks)} chunks on {n_workers} worker(s) at start"

    @property
    def n_facets(self) -> int:
        return self._n

    def solve(self, state, times_s, solar, E, ir0=None, prev=None, skip_K: float = 0.0, hold: bool = False):
        """As :meth:`waveform.LocalColumns.solve`; ``prev`` must be the result of this backend's latest call
        (its chunks' parts stay on the workers and are used there)."""
        if prev is None:
            self._last = self._state = None
        skip = skip_K if prev is not None else 0.0
        return _resending(
            self.client, lambda: self._round(state, times_s, solar, E, ir0, skip, hold), _RESUME, self._forget
        )

    def _forget(self) -> None:
        """After a lost input: the next attempt sends the window's start and sunlight again."""
        self._last = self._state = None

    def relax_window(self, state, times_s, solar, ir0, emissivity: float, tol_K: float, max_iter: int):
        """:func:`waveform.relax` of one window kept on the workers (the same iterations and results): after
        the first iteration, each chunk's next emission and its largest change since the previous iteration
        are formed where its window is, the chunks fetch each other's emission from the workers, and only
        one number per chunk comes back per iteration; the surface temperatures come back once, with the
        converged window. A lost worker sends the window again from its start."""
        args = (state, times_s, solar, ir0, float(emissivity), float(tol_K), int(max_iter))
        return _resending(self.client, lambda: self._relax(*args), _RESUME, self._forget)

    def _relax(self, state, times_s, solar, ir0, emissivity: float, tol_K: float, max_iter: int):
        client, chunks = self.client, self.chunks
        n = len(times_s)
        self._last = None
        self._send_window(state, solar)
        facets = client.scatter(_Facets(chunks), hash=False)
        T0 = np.asarray(state)[:, 0]
        # the start's emission held over the window: one row sent, in the type of the window's products
        E = client.scatter(_Broadcast(_operand(radiosity.emitted(T0, emissivity)[None, :], n)[0], n), hash=False)
        skip = waveform.SKIP_FRACTION * tol_K
        last = [None] * len(chunks)
        change = np.inf
        futures = self._iteration(solve_chunk_parts, E, times_s, ir0, last, skip, False, facets)
        for it in range(1, max_iter + 1):
            # the next iteration is submitted before this one's convergence is known, so that the workers go
            # on while this process hears of it: its tasks first look at this iteration's changes and do
            # nothing once every chunk's is within the tolerance (:func:`solve_chunk_parts`'s ``stop``)
            changes = None if it == 1 else [client.submit(_change, f, p, pure=False) for f, p in zip(futures, last)]
            following = None
            if it < max_iter:
                E = [client.submit(_emission, f, emissivity, pure=False) for f in futures]
                stop = None if changes is None else (changes, float(tol_K))
                following = self._iteration(solve_chunk_parts, E, times_s, ir0, futures, skip, False, facets, stop)
            if changes is not None:
                change = float(max(client.gather(changes)))
                if change <= tol_K:
                    parts = client.gather([client.submit(_surface, f, pure=False, retries=RETRIES) for f in futures])
                    self._last = futures
                    return _RemoteWindow(self, futures, parts, n), it, change
            last, futures = futures, following
        raise waveform.not_converged(max_iter, change, tol_K)

    def lagged_pass(self, state, times_s, rows, block: int, previous, on_step=None, skip=None):
        """:meth:`_lagged_pass`, with dask's failures turned into one-line errors, or into
        :class:`waveform.PassLost` when data of the pass went with a worker (the caller runs the pass again
        through the command)."""
        return self._whole_pass(self._lagged_pass, state, times_s, rows, block, previous, on_step, skip)

    def next_inputs(self):
        """The next lagged pass's input IR formed on the workers from the latest pass's temperatures (per
        block and chunk, kept there for that pass: the products it would make itself); returns (the largest
        change from the latest pass's input [W m-2], the coldest surface temperature [K]) per facet
        (one exchange), or None when data of the pass is lost (that pass then runs every column). The
        tasks were submitted at the pass's end (:meth:`_pass_end`), so they ran while this process made
        its quasi-Newton step."""
        ahead, self._ahead = self._ahead, None
        try:
            nxt, summaries = ahead if ahead is not None else self._next_tasks()
            dq, t_min = np.empty(self._n), np.empty(self._n)
            for idx, (d, t) in zip(self.chunks, self.client.gather(summaries)):
                dq[idx], t_min[idx] = d, t
        except (CraterThermalError, MemoryError):
            raise
        except Exception:  # a worker lost with data of the pass: the next pass finds out and falls back
            self._next = None
            return None
        self._next = nxt
        return dq, t_min

    def _next_tasks(self):
        """The tasks of :meth:`next_inputs` (submitted, not gathered): ``({b0: each chunk's input of the
        block}, each chunk's summary)``."""
        client, chunks = self.client, self.chunks
        nxt = {
            b0: [
                client.submit(
                    _next_ir, self.row_futures[c], self._chunks_f, self._surfaces[b0], w, self.options, pure=False
                )
                for c, w in enumerate(windows)
            ]
            for b0, windows in self._pass.items()
        }
        summaries = [client.submit(_drift_summary, *[nxt[b0][c] for b0 in nxt], pure=False) for c in range(len(chunks))]
        return nxt, summaries

    def _cancel_ahead(self) -> None:
        """Drop the next inputs' tasks submitted ahead (the start has converged: no next pass)."""
        ahead, self._ahead = self._ahead, None
        if ahead is not None:
            self.client.cancel([f for futs in ahead[0].values() for f in futs] + list(ahead[1]))

    def held_pass(self, state, times_s, rows, block: int, on_step=None):
        """:meth:`_held_pass`, with dask's failures turned into one-line errors or :class:`waveform.PassLost`
        (as :meth:`lagged_pass`)."""
        return self._whole_pass(self._held_pass, state, times_s, rows, block, on_step)

    def _whole_pass(self, run, *args):
        from distributed import KilledWorker

        try:
            return run(*args)
        except KilledWorker as exc:
            raise _gave_up(exc) from None
        except (CraterThermalError, MemoryError):
            raise
        except Exception as exc:
            self.end_spinup()
            if not _workers_left(self.client):
                raise _failed(exc) from None
            raise waveform.PassLost(str(exc)) from None

    def _lagged_pass(self, state, times_s, rows, block: int, previous, on_step=None, skip=None):
        """One lagged pass of the periodic start (:meth:`waveform.SpinUp.lagged`) kept on the workers: the
        whole pass is submitted at once (each chunk's block starts from its block before), each task
        builds the emission from the previous pass's temperatures, worker to worker, and only the end
        states, accumulators and last IR come back. ``previous(k0, k1)``: the previous pass's temperature
        rows [K] from the command's store, used when no pass has run on the workers yet. ``skip`` (bool
        (nf,)): columns not to run (they keep the previous pass's windows), with the input IR formed by
        :meth:`next_inputs`.

        Returns (end state (nf, nz) [K], accumulators (nf, n_acc), IR at the last sample (nf,) [W m-2]).
        """
        client, chunks = self.client, self.chunks
        n = len(times_s)
        blocks = self._send_spin(times_s, rows, block)
        start = client.scatter([np.ascontiguousarray(state[idx]) for idx in chunks], hash=False)
        new, surfaces = {}, {}
        nxt, self._next = self._next, None
        run = [None] * len(chunks)
        if skip is not None and nxt is not None and np.any(skip):
            run = [np.flatnonzero(~np.asarray(skip)[idx]) for idx in chunks]
        for b0, b1 in blocks:
            if nxt is not None:
                source = nxt[b0]
            elif self._surfaces is None:
                source = [client.scatter(np.ascontiguousarray(previous(b0, b1 + 1)), hash=False)] * len(chunks)
            else:
                source = [self._surfaces[b0]] * len(chunks)
            futs = [
                client.submit(
                    lagged_chunk,
                    self.row_futures[c],
                    self._chunks_f,
                    c,
                    source[c],
                    start[c],
                    times_s[b0 : b1 + 1],
                    self._spin[b0][c],
                    self.options,
                    run[c],
                    None if run[c] is None else self._pass[b0][c],
                    pure=False,
                    retries=RETRIES,
                )
                for c in range(len(chunks))
            ]
            new[b0], start = futs, futs
            surfaces[b0] = [client.submit(_surface, f, pure=False) for f in futs]
        return self._pass_end(new, surfaces, blocks, n, on_step)

    def _send_spin(self, times_s, rows, block: int) -> list[tuple[int, int]]:
        """The blocks ``(b0, b1)`` of a spin-up pass; the spin-up window's sunlight (per block and chunk) and
        the chunking sent to the workers once for all passes."""
        n = len(times_s)
        blocks = [(b0, min(n - 1, b0 + block)) for b0 in range(0, n - 1, block)]
        if self._spin is None:
            client, chunks = self.client, self.chunks
            self._chunks_f = client.scatter(_Facets(chunks), hash=False)
            self._spin = {
                b0: client.scatter([_compact(rows(b0, b1 + 1)[:, idx]) for idx in chunks], hash=False)
                for b0, b1 in blocks
            }
        return blocks

    def _held_pass(self, state, times_s, rows, block: int, on_step=None):
        """The first pass of the periodic start (:meth:`waveform.SpinUp.held`) kept on the workers, submitted
        whole: per hold (:func:`waveform.hold_spans`), each chunk's task forms its rows' IR from the surface
        temperatures every chunk reached at the hold's start (worker to worker: one float per facet) and
        conducts its columns through the hold with that IR, in the first pass's coarse steps
        (:func:`waveform.held_window`, as in one process); the holds of a block are joined into the
        block's window, whose temperatures drive the next (lagged) pass on the workers. Only the end
        states, accumulators and last IR come back (as :meth:`_lagged_pass`).

        Returns (end state (nf, nz) [K], accumulators (nf, n_acc), IR at the last sample (nf,) [W m-2]).
        """
        client, chunks = self.client, self.chunks
        n = len(times_s)
        blocks = self._send_spin(times_s, rows, block)
        start = client.scatter([np.ascontiguousarray(state[idx]) for idx in chunks], hash=False)
        source = client.scatter(np.ascontiguousarray(state[:, 0]), hash=False)  # the surfaces at the start
        new, surfaces = {}, {}
        for b0, b1 in blocks:
            holds = []
            for k, k1 in waveform.hold_spans(times_s, b0, b1):
                futs = [
                    client.submit(
                        held_chunk,
                        self.row_futures[c],
                        self._chunks_f,
                        c,
                        source,
                        start[c],
                        times_s[k : k1 + 1],
                        self._spin[b0][c],
                        k - b0,
                        self.options,
                        pure=False,
                        retries=RETRIES,
                    )
                    for c in range(len(chunks))
                ]
                source = [client.submit(_last_surface, f, pure=False) for f in futs]
                holds.append(futs)
                start = futs
            new[b0] = [client.submit(_joined, *[h[c] for h in holds], pure=False) for c in range(len(chunks))]
            surfaces[b0] = [client.submit(_surface, f, pure=False) for f in new[b0]]
        return self._pass_end(new, surfaces, blocks, n, on_step)

    def _pass_end(self, new, surfaces, blocks, n: int, on_step):
        """Gather a pass's end (end states, accumulators, last IR) and keep its windows on the workers."""
        client, chunks, nf = self.client, self.chunks, self._n
        summaries = [
            client.submit(_pass_summary, *[new[b0][c] for b0, _ in blocks], pure=False) for c in range(len(chunks))
        ]
        self._pass, self._surfaces = new, surfaces
        try:  # the next pass's inputs, ahead: the workers form them while this process takes its step
            self._ahead = self._next_tasks()
        except (CraterThermalError, MemoryError):
            raise
        except Exception:  # made (or found lost) when asked for
            self._ahead = None
        end = acc = None
        ir_end = np.empty(nf)
        for idx, (e, a, last_ir) in zip(chunks, client.gather(summaries)):
            if end is None:
                end, acc = np.empty((nf, e.shape[1])), np.empty((nf, a.shape[1]))
            end[idx], acc[idx], ir_end[idx] = e, a, last_ir
        if on_step is not None:
            on_step(n - 1)
        return end, acc, ir_end

    def pass_ir(self, k0: int, k1: int):
        """IR rows [W m-2] ``k0..k1-1`` of the latest lagged pass, gathered from the workers (each block
        owns its rows but the last, which is the next block's first, except at the end); only the blocks
        that hold those rows are asked, and only for them. In ``run.nc``'s type
        (:data:`crater_thermal.io.RUN_SERIES_DTYPE`: they are kept for it only), half the bytes."""
        self._cancel_ahead()  # asked for once the start has converged: no next pass needs them
        out = []
        starts = sorted(self._pass)
        for i, b0 in enumerate(starts):
            own_end = starts[i + 1] if i + 1 < len(starts) else None  # None: the last block owns all its rows
            if b0 >= k1:
                break
            if own_end is not None and own_end <= k0:
                continue
            lo, hi = max(k0, b0) - b0, k1 - b0 if own_end is None else min(k1, own_end) - b0
            futs = [self.client.submit(_ir_part, f, lo, hi, pure=False) for f in self._pass[b0]]
            parts = self.client.gather(futs)
            rows = np.empty((len(parts[0]), self._n), io.RUN_SERIES_DTYPE)
            for idx, p in zip(self.chunks, parts):
                rows[:, idx] = p
            out.append(rows)
        return np.concatenate(out)

    def end_spinup(self) -> None:
        """Release the spin-up's data on the workers."""
        self._cancel_ahead()
        self._pass = self._surfaces = self._spin = self._chunks_f = self._next = None

    def _send_window(self, state, solar) -> None:
        """A window's start state (nf, nz) [K] and sunlight rows (n, nf) [W m-2] to the workers, per chunk."""
        self._state = self.client.scatter([np.ascontiguousarray(state[idx]) for idx in self.chunks], hash=False)
        self._solar = self.client.scatter([_compact(solar[:, idx]) for idx in self.chunks], hash=False)

    def _iteration(self, task, E, times_s, ir0, last, skip_K: float, *tail) -> list:
        """One iteration's tasks, one per chunk: ``task(rows, facets, E, state, times_s, solar, ir0, options,
        prev, skip_K, *tail)`` with the window's start state and sunlight already on the workers and ``last``
        the chunks' previous iterates (or None each)."""
        return [
            self.client.submit(
                task,
                self.row_futures[c],
                idx,
                E,
                self._state[c],
                times_s,
                self._solar[c],
                None if ir0 is None else ir0[idx],
                self.options,
                last[c],
                skip_K if last[c] is not None else 0.0,
                *tail,
                pure=False,
                retries=RETRIES,
            )
            for c, idx in enumerate(self.chunks)
        ]

    def _round(self, state, times_s, solar, E, ir0, skip_K, hold=False):
        client = self.client
        if self._state is None:  # a new window (or a resent one): its start state and sunlight, once
            self._send_window(state, solar)
        # one copy, on one worker; the others fetch it from there (a broadcast scatter waits on a worker
        # that died mid-replication: measured, 30 s retries until the end); in the products' type
        E_f = client.scatter(_operand(E, len(E)), hash=False)
        futures = self._iteration(solve_chunk, E_f, times_s, ir0, self._last or [None] * len(self.chunks), skip_K, hold)
        # only the temperatures and the active counts come back each iteration (for the next emission and
        # the convergence test); IR, end states and accumulators stay on the workers until asked for
        parts = client.gather([client.submit(_surface, f, pure=False, retries=RETRIES) for f in futures])
        self._last = futures
        return _RemoteWindow(self, futures, parts, len(times_s))


def _compact(X: np.ndarray) -> np.ndarray:
    """``X`` to send to the workers: as float32 where that holds it exactly (sunlight read from a run's
    store, which keeps it in float32: half the bytes), else as it is; the tasks take it back in float64."""
    X = np.ascontiguousarray(X)
    if X.dtype == np.float64:
        X32 = X.astype(np.float32)
        if np.array_equal(X32, X):
            return X32
    return X


class _Broadcast:
    """One row ``row`` (nf,) standing for ``n`` equal rows (the first iteration's emission of a window: the
    start's, held), sent instead of the (n, nf) array and made into it by the task."""

    def __init__(self, row: np.ndarray, n: int):
        self.row, self.n = row, int(n)

    def array(self) -> np.ndarray:
        return np.ascontiguousarray(np.broadcast_to(self.row, (self.n, len(self.row))))


def _operand(X: np.ndarray, k: int) -> np.ndarray:
    """An operand sent to the workers for products with ``k`` right-hand sides, in the type the row blocks
    multiply it in (:meth:`crater_thermal.vfoperator.RowBlock.apply`: ``vfoperator.PRODUCT_DTYPE`` for
    several, float64 for one): float32 halves the bytes sent and held per worker."""
    return np.ascontiguousarray(X, vfoperator.PRODUCT_DTYPE if k > 1 else np.float64)


def _surface(w):
    """A chunk window's surface temperatures [K] and conducted-column count (a small task)."""
    return w.T, w.active


def _next_ir(rows, chunks, surfaces, w, options: dict):
    """A chunk's input IR [W m-2] of the next lagged pass over a block, from every chunk's surface
    temperatures [K] of the latest pass (``surfaces``: their ``(T, active)`` parts), with its change from
    the chunk's latest input (``w``: its window of the block) and the chunk's coldest surface temperature
    [K]: ``(ir, the largest absolute change per column, min T per column)``."""
    T = _joined_columns([np.asarray(t_part, float) for t_part, _ in surfaces], chunks)
    E = radiosity.emitted(T, options["emissivity"])
    with cluster.one_numba_thread():
        ir = np.zeros_like(w.ir) if rows is None else np.maximum(rows.apply(E.T).T, 0.0)
    return ir, np.max(np.abs(ir - w.ir), axis=0), np.min(w.T, axis=0)


def _drift_summary(*parts):
    """A chunk's largest absolute input change [W m-2] and coldest surface temperature [K] over all blocks."""
    return np.max([p[1] for p in parts], axis=0), np.min([p[2] for p in parts], axis=0)


def _last_surface(w):
    """A chunk window's surface temperatures [K] at its last sample (a small task)."""
    return w.T[-1]


def held_chunk(rows, chunks, c: int, source, start, times_s, solar, i0: int, options: dict):
    """One chunk through one hold of a periodic start's first pass (runs on a worker, one thread): its IR
    held at its rows' ``F e(T)`` of every facet's surface temperature [K] at the hold's start (``source``:
    one (nf,) array, or every chunk's part), from ``start`` (a state array, or the chunk's window of the
    hold before); ``solar`` the chunk's sunlight rows of the block [W m-2], the hold's from row ``i0``.
    Stepped as in one process (:func:`waveform.held_window`): to the samples of
    :func:`waveform.hold_samples` with coarse sub-steps, the others filled in; a window of every sample
    of the hold."""
    if isinstance(source, np.ndarray):
        T = source
    else:
        T = np.empty(sum(len(idx) for idx in chunks.idx))
        for idx, part in zip(chunks.idx, source):
            T[idx] = part
    state = start.end if isinstance(start, waveform.Window) else start
    E = radiosity.emitted(T, options["emissivity"])[None, :]
    sol = solar[i0 : i0 + len(times_s)]
    m = len(chunks.idx[c])

    def solve(times, solar_rows):
        return _chunk_window(rows, E, m, None, state, times, solar_rows, options, hold=True)

    with cluster.one_numba_thread():
        return waveform.held_window(solve, times_s, sol)


def _joined(*windows):
    """The holds of a block joined into one window (consecutive holds share a sample, the later one's
    first)."""
    last = windows[-1]
    T = np.concatenate([w.T[:-1] for w in windows[:-1]] + [last.T])
    ir = np.concatenate([w.ir[:-1] for w in windows[:-1]] + [last.ir])
    return waveform.Window(T, ir, last.end, sum(w.acc for w in windows))


def lagged_chunk(rows, chunks, c: int, source, start, times_s, solar, options: dict, run=None, prev=None):
    """One chunk through one block of a lagged spin-up pass (runs on a worker, one thread): driven by the IR
    of the previous pass's temperatures of every facet over the block, from ``start`` (a state array, or
    the chunk's window of the block before in this pass).

    ``source``: the previous pass's surface temperatures [K] over the block, as one (n, nf) array or as
    every chunk's ``(T, active)`` part (``chunks`` gives their facets); or the chunk's input IR formed by
    :func:`_next_ir` (a tuple). ``run``: the chunk's columns to run [indices] (the others keep ``prev``,
    the chunk's window of the block in the previous pass), or None: all.
    """
    state = start.end if isinstance(start, waveform.Window) else start
    if isinstance(source, tuple):  # the input IR, formed between the passes
        ir = source[0]
        solar = np.asarray(solar, np.float64)  # sent in float32 where that held it exactly (:func:`_compact`)
        a = radiosity.absorbed_flux(solar, ir, options["albedo"], options["emissivity"], options["solar_is_absorbed"])
        if run is not None:
            prev = waveform.Window(prev.T, ir, prev.end, np.zeros_like(prev.acc))
        with cluster.one_numba_thread():
            solver = _solver(options, len(chunks.idx[c]))
            return waveform.conduct(solver, state, times_s, a, ir, prev, 0.0, options["emissivity"], active=run)
    chunks = chunks.idx
    if isinstance(source, np.ndarray):
        T = source
    else:
        T = np.empty((len(times_s), sum(len(idx) for idx in chunks)))
        for idx, (t_part, _) in zip(chunks, source):
            T[:, idx] = t_part
    E = radiosity.emitted(T, options["emissivity"])
    with cluster.one_numba_thread():
        return _chunk_window(rows, E, len(chunks[c]), None, state, times_s, solar, options)


class _Facets:
    """The chunks' facet indices, as one object (dask would scatter a list element by element)."""

    def __init__(self, idx):
        self.idx = idx


def _pass_summary(*windows):
    """A chunk's pass: (end state [K], summed accumulators, IR [W m-2] at the last sample)."""
    return windows[-1].end, sum(w.acc for w in windows), windows[-1].ir[-1]


def _rest(w):
    """A chunk window's IR [W m-2], end state [K] and accumulators: what the command has not got (a small
    task; the temperatures came with :func:`_surface`)."""
    return w.ir, w.end, w.acc


def _ir_part(w, lo: int, hi: int):
    """Rows ``lo..hi-1`` of a chunk window's IR [W m-2] in ``run.nc``'s type (a small task)."""
    return w.ir[lo:hi].astype(io.RUN_SERIES_DTYPE)


class _RemoteWindow:
    """A window whose chunks' results are on the workers: ``T`` and ``active`` here, ``ir``, ``end`` and
    ``acc`` gathered on first use (see :class:`waveform.Window`)."""

    def __init__(self, owner: DaskColumns, futures, parts, n: int):
        self._owner, self._futures = owner, futures
        nf = owner.n_facets
        self.T = np.empty((n, nf))
        self.active = 0
        for idx, (t_c, act) in zip(owner.chunks, parts):
            self.T[:, idx] = t_c
            self.active += act if act >= 0 else len(idx)
        self._full = None

    def _fetch(self):
        if self._full is None:
            client = self._owner.client
            parts = client.gather([client.submit(_rest, f, pure=False) for f in self._futures])
            nf, chunks = self._owner.n_facets, self._owner.chunks
            ir = np.empty_like(self.T)
            end = np.empty((nf, parts[0][1].shape[1]))
            acc = np.empty((nf, parts[0][2].shape[1]))
            for idx, (w_ir, w_end, w_acc) in zip(chunks, parts):
                ir[:, idx], end[idx], acc[idx] = w_ir, w_end, w_acc
            self._full = (ir, end, acc)
        return self._full

    @property
    def ir(self):
        return self._fetch()[0]

    @property
    def end(self):
        return self._fetch()[1]

    @property
    def acc(self):
        return self._fetch()[2]


def build_rows(mesh_folder: str, a: int, b: int, settings: dict):
    """A chunk's rows ``a:b`` (cluster order) of the compressed operator, built on a worker from the mesh
    saved in ``mesh_folder`` without the rest of the operator (:meth:`vfoperator.CompressedPlan.row_block`),
    unscaled. A dask task: pure, so the scheduler builds it again elsewhere when its worker is lost."""
    with cluster.one_numba_thread():
        c0 = time.process_time()
        plan = _plan(mesh_folder, settings)
        plan_s = time.process_time() - c0
        block = plan.row_block(a, b, n_threads=1)
    block.stats["plan_cpu_s"] = plan_s  # the plan's CPU seconds when this task made it (else ~0)
    return block


def _plan(mesh_folder: str, settings: dict):
    """The worker's :class:`vfoperator.CompressedPlan` of the saved mesh (built once for all the chunks it
    builds; released by the first window it conducts, :func:`_chunk_window`)."""
    key = (mesh_folder, json.dumps(settings, sort_keys=True))  # the settings name the mesh's hash
    with _PLANS_LOCK:
        plan = _PLANS.get(key)
        if plan is None:
            plan = _PLANS[key] = _new_plan(mesh_folder, settings)
    return plan


def _new_plan(mesh_folder: str, settings: dict):
    """The plan of :func:`_plan`, built (the worker's earlier plans released first)."""
    _PLANS.clear()
    folder = Path(mesh_folder)
    mesh = geometry.Mesh(io.load_npy(folder / "vertices.npy"), io.load_npy(folder / "faces.npy"))
    if mesh.hash != settings["mesh_hash"]:
        raise ConfigError(
            f"the mesh in {folder} is not the run's (hash {mesh.hash}, expected {settings['mesh_hash']}): "
            "was the run's scratch folder changed by another run? Run again with --overwrite"
        )
    tracer = raytrace.RayTracer(mesh, n_threads=1)
    return vfoperator.CompressedPlan(mesh, tracer, settings["tolerance"], tolerance_mode=settings["tolerance_mode"])


def _summary(block):
    """A chunk's facets (its rows, cluster order) and their row sums [-] unscaled (a small task)."""
    return block.facets, block.row_sums()


def _scale_of(*summaries):
    """The rescaling of every row [-] (cluster order) from all chunks' row sums, or None (one task)."""
    return vfoperator.rowsum_scale(np.concatenate([s for _, s in summaries]))[0]


def _scaled(block, scale):
    """A chunk's rows with the operator's rescaling (the arrays shared, not copied)."""
    return block.with_scale(scale)


def _apply_rows(block, X):
    """``(F @ X)`` on a chunk's rows (a product of :class:`ClusterOperator`), sent back in float32 where
    that holds it exactly (several right-hand sides are multiplied in float32: :func:`_compact`)."""
    with cluster.one_numba_thread():
        return _compact(block.apply(X))


def _workers_left(client) -> bool:
    """True when the cluster has a worker, or one joins within :func:`worker_wait_s`."""
    try:
        client.wait_for_workers(1, timeout=worker_wait_s())
        return True
    except Exception:  # dask's TimeoutError
        return False


class ClusterOperator(vfoperator.ViewFactorOperator):
    """The view-factor operator of a run whose rows are held by the workers (the chunks' row blocks):
    what the command's process uses for the products it needs (scattered sunlight, the start's IR)
    without the operator. ``F @ X``: ``X`` is sent once (to one worker; the others fetch it from there),
    each chunk's task returns its rows, assembled here. ``F^T y = A F (y / A)`` (``A`` the facet areas,
    reciprocity: ``diag(A) F`` is symmetric).

    Parameters
    ----------
    client : the dask client; rows : the chunks' row-block futures; bounds : their row ranges ``(a, b)``
    in ``order`` (the cluster order, facet indices); areas : (n,) facet areas [m2]; rowsums : (n,) the
    unscaled row sums [-] (facet order); held : bytes of the row blocks on the workers [B].
    """

    kind = "compressed"
    asynchronous = True

    def __init__(self, client, rows, bounds, order, areas, rowsums, held: int):
        n = len(order)
        self.shape = (n, n)
        self.client, self.rows, self.bounds = client, rows, bounds
        self.order = np.asarray(order, np.int64)
        self.areas = np.asarray(areas, np.float64)
        self.rowsum_excess = vfoperator.rowsum_scale(rowsums)[1]
        self._zero = not np.any(rowsums)
        #: bytes of the row blocks on the workers (all chunks) [B]
        self.held_bytes = int(held)

    @property
    def nbytes(self) -> int:
        """Bytes held by this process [B] (the facet order and areas; the rows are on the workers)."""
        return int(self.order.nbytes + self.areas.nbytes)

    @property
    def is_zero(self) -> bool:
        return self._zero

    def matvec(self, x):
        x = self._check(x)
        return self._products(x.reshape(x.shape[0], -1)).reshape(x.shape)

    def rmatvec(self, y):
        y = self._check(y)
        a = self.areas[:, None]
        return (self._products(y.reshape(y.shape[0], -1) / a) * a).reshape(y.shape)

    def submit(self, x):
        """``F x`` begun on the workers (the operand sent, each chunk's rows' task submitted): ``result()``
        gathers and assembles it, with :func:`_resending`'s rules (an input lost with a worker: the product
        made again; a task's own error: raised as it is)."""
        x = self._check(x)
        X = x.reshape(x.shape[0], -1)
        try:
            futures = self._submitted(X)
        except (CraterThermalError, InternalError, MemoryError):
            raise
        except Exception:  # the cluster failed the send: result() sends it again, or gives up
            futures = None
        return _Product(self, X, futures, x.shape)

    def _submitted(self, X) -> list:
        client = self.client
        X_f = client.scatter(_operand(X, X.shape[1]), hash=False)
        return [client.submit(_apply_rows, r, X_f, pure=False, retries=RETRIES) for r in self.rows]

    def _products(self, X):
        return _Product(self, X, None, X.shape).result()


class _Product:
    """A product of a :class:`ClusterOperator`: ``X`` (n, k) [any unit], its tasks already submitted
    (``futures``) or None; ``result()`` in ``shape``."""

    def __init__(self, op: ClusterOperator, X: np.ndarray, futures, shape):
        self.op, self.X, self.futures, self.shape = op, X, futures, shape

    def result(self) -> np.ndarray:
        op = self.op

        def attempt():
            futures, self.futures = self.futures, None  # the tasks in flight first, then sent again
            parts = op.client.gather(futures if futures is not None else op._submitted(self.X))
            out = np.empty_like(self.X, dtype=np.float64)
            for (a, b), part in zip(op.bounds, parts):
                out[op.order[a:b]] = part
            return out.reshape(self.shape)

        return _resending(op.client, attempt)


class _Session:
    """A run's dask cluster from the view factors to the end of the record (what
    :func:`distributed_columns` yields to :func:`crater_thermal.runner.run_case`): the operator's row
    blocks are built on the workers (:meth:`view_factors`), then conducted with (:meth:`columns`)."""

    def __init__(self, client, case, mesh, store, chunk_facets: int | None):
        self.client, self.case, self.store = client, case, store
        nf = self.nf = mesh.n_facets
        self.n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        # one chunk per worker by default: the fewest tasks per iteration, and the fewest far blocks that
        # two chunks share (each is built and applied by both; measured in docs/cluster.md)
        size = -(-nf // self.n_workers)
        if chunk_facets is not None:
            size = min(int(chunk_facets), size)
        self.bounds = [(a, min(nf, a + size)) for a in range(0, nf, size)]
        self.order = np.arange(nf, dtype=np.int64)
        self.rows = [None] * len(self.bounds)
        self.tag = f"{hashlib.sha256(f'{store.folder}:{nf}:{size}'.encode()).hexdigest()[:8]}-{uuid.uuid4().hex[:8]}"

    def view_factors(self, mesh, tracer, method: str, tolerance: float, cache_dir=None, progress=None):
        """The run's operator (as :func:`vfoperator.view_factor_operator`, same arguments). Compressed:
        built on the workers, each chunk's rows by the worker that holds them, and a
        :class:`ClusterOperator` of them back; this process never holds the whole operator. Exact (small
        by construction): built here (cached as a local run does), saved into the scratch store and
        loaded by the workers row block by row block."""
        if method == "compressed":
            return self._build_on_workers(mesh, tolerance, progress)
        F = vfoperator.view_factor_operator(
            mesh, tracer, method=method, tolerance=tolerance, cache_dir=cache_dir, progress=progress
        )
        folder = Path(self.store.folder).resolve() / "operator"
        if not self.store.marked("operator"):
            vfoperator.save_operator(F, folder)
            self.store.mark("operator")
        self.order = vfoperator.row_order(F)
        self.rows = [
            self.client.submit(load_rows, str(folder), a, b, key=f"ct-rows-{self.tag}-{a}") for a, b in self.bounds
        ]
        return F

    def _build_on_workers(self, mesh, tolerance: float, progress=None):
        from distributed import KilledWorker, as_completed

        client, bounds, tag = self.client, self.bounds, self.tag
        folder = Path(self.store.folder).resolve() / "mesh"
        if not self.store.marked("mesh"):  # written once: a resumed run's mesh is the same (the case's fingerprint)
            folder.mkdir(parents=True, exist_ok=True)
            np.save(folder / "vertices.npy", mesh.vertices)
            np.save(folder / "faces.npy", mesh.faces)
            self.store.mark("mesh")
        settings = {"tolerance": float(tolerance), "tolerance_mode": "block", "mesh_hash": mesh.hash}
        try:
            raw = [
                client.submit(build_rows, str(folder), a, b, settings, key=f"ct-build-{tag}-{a}", retries=RETRIES)
                for a, b in bounds
            ]
            # the client keeps the row sums and the scale (n floats): a lost block is built again from
            # them and the mesh, never from all the other blocks
            starts = [a for a, _ in bounds]
            self._sums = [client.submit(_summary, r, key=f"ct-rowsum-{tag}-{a}") for r, a in zip(raw, starts)]
            self._scale = client.submit(_scale_of, *self._sums, key=f"ct-scale-{tag}")
            self.rows = [client.submit(_scaled, r, self._scale, key=f"ct-rows-{tag}-{a}") for r, a in zip(raw, starts)]
            del raw
            for done, _ in enumerate(as_completed(self._sums), 1):
                if progress is not None:
                    progress(done, len(bounds))
            summaries = client.gather(self._sums)
            held = sum(client.gather([client.submit(_nbytes, r, pure=False) for r in self.rows]))
        except KilledWorker as exc:
            raise _gave_up(exc) from None
        # the cluster order (the chunks' facets) and the row sums, n numbers each
        self.order = np.concatenate([f for f, _ in summaries])
        rowsums = np.empty(self.nf)
        rowsums[self.order] = np.concatenate([s for _, s in summaries])
        return ClusterOperator(client, self.rows, bounds, self.order, mesh.areas, rowsums, held)

    def columns(self, fc):
        """The waveform-relaxation backend (:class:`DaskColumns`) of the run's chunks."""
        case = self.case
        options = {
            "profile": case.surface.nominal_profile,
            **runner.column_settings(case),
            "albedo": float(case.surface.albedo),
            "solar_is_absorbed": case.surface.albedo_model != "constant",
        }
        rows = self.rows if fc.F is not None else [None] * len(self.bounds)
        chunks = [self.order[a:b] for a, b in self.bounds]
        cols = DaskColumns(self.client, chunks, rows, options, self.nf, self.n_workers)
        if isinstance(fc.F, ClusterOperator):
            cols.description += f"; operator rows built by the workers ({fc.F.held_bytes / 1e6:.1f} MB in all)"
        return cols


def _nbytes(block) -> int:
    return block.nbytes


def distributed_columns(scheduler=None, workers=None, chunk_facets: int | None = None):
    """The ``columns`` factory of :func:`crater_thermal.runner.run_case` for a dask cluster: the scheduler at
    ``scheduler`` (``tcp://host:8786``) or a local cluster of ``workers`` one-thread processes;
    ``chunk_facets``: at most that many facets per chunk (None: one chunk per worker, :class:`_Session`)."""
    if chunk_facets is not None and int(chunk_facets) < 1:
        raise ConfigError(f"--chunk-facets {chunk_facets}: chunks need at least 1 facet")

    @contextlib.contextmanager
    def factory(case, mesh, store):
        client, cl = cluster.connect(scheduler, workers, "runs on a dask cluster (--scheduler, --workers)")
        try:
            yield _Session(client, case, mesh, store, chunk_facets)
        finally:
            cluster.disconnect(client, cl)

    return factory
