"""Waveform relaxation: the coupled IR exchange solved a window of samples at a time, columns apart.

The coupled stepper (:class:`crater_thermal.radiosity.CoupledStepper`) exchanges IR between all columns at
every flux step, so every column waits for every other at every step: one process. Waveform relaxation
integrates every column over a whole *window* of samples with the emission of the previous iterate held as
a known series, then recomputes the IR of every sample of the window from the new temperatures (one
product with as many right-hand sides as samples), and repeats::

    T(m+1) = conduct(state at the window's start, solar, IR = F e(T(m)))   over the window

until ``max |T(m+1) - T(m)| <= tol_K`` over the window's samples and columns. Within an iteration the
columns are independent, and the IR of a column needs only its own row of ``F``: the distributed run
(:mod:`crater_thermal.cluster_run`) gives each worker some columns and the operator's rows of those
columns, and exchanges only the window's emission (samples x facets) per iteration.

Fixed point: the IR at every sample is ``F e(T)`` of the temperatures it produced, with the absorbed flux
linear in time between samples, which is the implicit coupling the stepper's schemes approximate (their
per-step defect test, ``radiosity.IR_DEFECT_W_M2``), so both agree within the two tolerances.

Convergence: an iteration multiplies a temperature error by about ``eps x`` (the facet's view of the
scene, ``F``'s row sum) ``x`` (the share of an absorbed-flux change that shows in the surface temperature
within the window); on crater terrain that factor is 0.1-0.3, so the change between iterations bounds the
remaining error (``change x q / (1 - q)``). The first iterate holds the emission of the window's start
state; measured iteration counts are in ``docs/cluster.md``.

Backends (``columns`` below) have ``n_facets`` and ``solve(state, times_s, solar, E, ir0)`` (see
:meth:`LocalColumns.solve`); :class:`LocalColumns` runs them in this process (the reference the
distributed backend is tested against).
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass

import numpy as np

from crater_thermal import radiosity, thermal
from crater_thermal.constants import SIGMA
from crater_thermal.errors import SolverError

#: Default convergence tolerance of a window [K]: the largest change of any surface temperature between
#: two iterations (the remaining error is a fraction of it, see the module docstring).
DEFAULT_TOL_K = 1e-3
#: The first pass of a periodic start holds each facet's IR for this long [s] before taking the IR of the
#: temperatures reached (one one-vector product per hold): a day is 1/30 of the lunar day, and the passes
#: after it then converge as after a coupled first pass (3,000 facets: residuals 2.5, 0.18, 0.024, 0.003 K
#: against 2.5, 0.18, 0.027, 0.004 K; holding 4 days took one pass more, a constant IR two). Used by both
#: lagged starts, this module's :class:`SpinUp` and :mod:`crater_thermal.simulate`'s.
FIRST_PASS_HOLD_S = 86400.0
#: The first pass steps at most this far [s] within a hold (every third sample of 4-hour steps), with
#: conduction sub-steps as long and no adaptive refinement (:func:`first_pass_steps`): it only seeds the
#: later passes, whose fixed point does not depend on it. Between the samples stepped to, its surface
#: temperatures are filled in so that their emission, and so the IR of the next pass, is linear in time
#: (:func:`between`). 0: every sample, with the solver's own sub-steps and refinement. Used by both lagged
#: starts (:meth:`SpinUp.held`, on a cluster too, and :mod:`crater_thermal.simulate`'s).
FIRST_PASS_STEP_S = 43200.0
#: Most iterations per window before the run stops with an error.
MAX_ITERATIONS = 30
#: After the first iteration of a window, a column is conducted again only when its new IR can move its
#: temperatures by more than this fraction of the tolerance (:func:`active_columns`); the others keep
#: their previous iterate (on crater terrain ~20 % of the columns take the later iterations).
SKIP_FRACTION = 0.25
#: Samples per window (16 days at 4 h), at most; fewer when the memory budget's block of samples is
#: shorter (:func:`window_samples`). The iterations a window needs grow with its length (5-7 at 24
#: samples, 7-8 at 96 on crater terrain), but the later ones conduct few columns, and a distributed run
#: exchanges once per iteration: measured in ``docs/cluster.md``.
DEFAULT_WINDOW = 96


def hold_spans(times_s, b0: int, b1: int, hold_s: float = FIRST_PASS_HOLD_S) -> list[tuple[int, int]]:
    """The holds of a first pass over samples ``b0 .. b1 - 1``: ``(k, k1)`` pairs, the IR held over samples
    ``k .. k1 - 1`` (the samples within ``hold_s`` [s] of sample k, at least one) and the next hold starting
    at ``k1 <= b1`` from the IR of the temperatures at sample ``k1``; ``times_s`` (n,) [s]."""
    spans = []
    k = int(b0)
    while k < b1:
        k1 = k + 1
        while k1 < b1 and times_s[k1] - times_s[k] < hold_s:
            k1 += 1
        spans.append((k, k1))
        k = k1
    return spans


def hold_samples(times_s, step_s: float | None = None) -> np.ndarray:
    """The samples a first pass's hold over ``times_s`` (n,) [s] (its samples, the next hold's first
    included) steps to: indices from 0 to n - 1, each the last sample at most ``step_s`` [s] (default
    :data:`FIRST_PASS_STEP_S`) after the one before, and at least the next one (0: every sample)."""
    step = FIRST_PASS_STEP_S if step_s is None else float(step_s)
    t = np.asarray(times_s, float)
    sub = [0]
    while sub[-1] < len(t) - 1:
        j = sub[-1] + 1
        while j < len(t) - 1 and t[j + 1] - t[sub[-1]] <= step:
            j += 1
        sub.append(j)
    return np.asarray(sub)


def between(times_s, known, values, rows, emission: bool = False) -> np.ndarray:
    """Rows of a first pass at samples ``rows`` (indices, within ``known[0] .. known[-1]``) from its rows
    ``values`` (m, nf) at the samples stepped to, ``known`` (m,) (increasing indices of ``times_s`` [s]):
    linear in time between them, or with ``emission`` (``values`` surface temperatures [K]) the
    temperatures whose emission ``eps sigma T^4`` is linear in time (so that the IR ``F e(T)`` the next
    pass forms from them is the IR of the stepped samples interpolated linearly, as
    :mod:`crater_thermal.simulate`'s lagged start forms it; the stepped samples' own values are kept)."""
    t, kk, v = np.asarray(times_s, float), np.asarray(known), np.asarray(values, float)
    rows = np.asarray(rows)
    left = np.clip(np.searchsorted(kk, rows, side="right") - 1, 0, len(kk) - 1)
    right = np.minimum(left + 1, len(kk) - 1)
    span = t[kk[right]] - t[kk[left]]
    w = np.where(span > 0, (t[rows] - t[kk[left]]) / np.where(span > 0, span, 1.0), 0.0)[:, None]
    if not emission:
        return (1.0 - w) * v[left] + w * v[right]
    P = v**2
    P *= P  # T^4 of the m stepped samples once, not of every row twice
    T4 = (1.0 - w) * P[left]
    T4 += w * P[right]
    np.sqrt(T4, out=T4)
    np.sqrt(T4, out=T4)  # the fourth root (a power of 0.25 costs ~4x more)
    at = w[:, 0] == 0.0
    T4[at] = v[left[at]]  # the stepped samples themselves
    return T4


@contextlib.contextmanager
def first_pass_steps(solver, on: bool = True, step_s: float | None = None):
    """Within: ``solver`` (a thermal.ColumnSolver) takes a first pass's coarse steps, sub-steps up to
    ``step_s`` [s] (default :data:`FIRST_PASS_STEP_S`) and no adaptive refinement; its settings are
    restored after. Nothing changes when ``on`` is false or the step is 0 (every sample)."""
    step = FIRST_PASS_STEP_S if step_s is None else float(step_s)
    if not on or step <= 0:
        yield solver
        return
    dt_max, adapt_K = solver.dt_max, solver.adapt_K
    solver.dt_max, solver.adapt_K = max(dt_max, step), 0.0
    try:
        yield solver
    finally:
        solver.dt_max, solver.adapt_K = dt_max, adapt_K


def held_window(solve, times_s, solar, step_s: float | None = None) -> Window:
    """One hold of a periodic start's first pass over the samples ``times_s`` (n,) [s] with sunlight rows
    ``solar`` (n, m) [W m-2]: ``solve(times, solar_rows)`` conducts the columns with their IR held (a
    backend's ``solve(..., hold=True)``, which steps coarsely: :func:`first_pass_steps`) to the samples of
    :func:`hold_samples` only; the :class:`Window` of every sample, its surface temperatures between the
    stepped samples filled in by :func:`between` (emission linear in time) and the held IR repeated."""
    sub = hold_samples(times_s, step_s)
    w = solve(np.asarray(times_s)[sub], solar[sub])
    n = len(times_s)
    if len(sub) == n:
        return w
    T = between(times_s, sub, w.T, np.arange(n), emission=True)
    return Window(T, held_ir(np.asarray(w.ir), n, True), w.end, w.acc, w.active)


def window_samples(block: int) -> int:
    """Samples per relaxation window for a memory budget of ``block`` samples per (time, facet) block."""
    return max(2, min(DEFAULT_WINDOW, int(block)))


class PassLost(Exception):
    """A backend lost data of a lagged pass (a worker died): the pass is to be run again another way."""


@dataclass
class Window:
    """The result of one pass of the columns over a window of n samples.

    Attributes
    ----------
    T : (n, nf) surface temperatures [K]; row 0 is the start state's.
    ir : (n, nf) the IR irradiance [W m-2] that drove the pass (row 0: the given start IR).
    end : (nf, nz) the columns' state at the window's last sample [K].
    acc : (nf, n_acc) the conduction kernel's accumulators of the pass (for ``thermal.periodic_state``).
    """

    T: np.ndarray
    ir: np.ndarray
    end: np.ndarray
    acc: np.ndarray
    #: columns conducted in this pass (the others kept the previous iterate's results)
    active: int = -1


class LocalColumns:
    """Every facet's column in this process.

    Parameters
    ----------
    solver : thermal.ColumnSolver with one column per facet (its state is overwritten by each solve).
    F : view-factor operator (``F @ X`` for X (nf, k)), or None for no exchange.
    albedo, emissivity : [-]
    solar_is_absorbed : the solar rows are already absorbed sunlight [W m-2] (incidence-dependent albedo).
    """

    def __init__(self, solver, F, albedo: float, emissivity: float, solar_is_absorbed: bool = False):
        self.solver, self.F = solver, F
        self.albedo, self.emissivity, self.solar_is_absorbed = float(albedo), float(emissivity), solar_is_absorbed

    @property
    def n_facets(self) -> int:
        return self.solver.ncol

    def solve(
        self, state, times_s, solar, E, ir0=None, prev: Window | None = None, skip_K: float = 0.0, hold: bool = False
    ) -> Window:
        """Conduct the columns over the window from ``state``.

        Parameters
        ----------
        state : (nf, nz) [K] at ``times_s[0]``.
        times_s : (n,) [s].
        solar : (n, nf) sunlight rows [W m-2] (incident, or absorbed with ``solar_is_absorbed``).
        E : (n, nf) emitted flux [W m-2] whose IR ``F E`` drives samples 1..n-1 (and sample 0 when
            ``ir0`` is None).
        ir0 : (nf,) the IR [W m-2] at sample 0, or None.
        prev, skip_K : the previous iterate of the same window and a temperature change [K]: the columns
            whose IR changed so little since ``prev`` that their temperatures cannot move by more than
            ``skip_K`` (:func:`active_columns`) keep ``prev``'s results instead of being conducted again.
        hold : ``E`` is one row (1, nf) whose IR ``F E`` is held over every sample (a first pass's hold,
            :meth:`SpinUp.held`: one one-vector product), conducted with the first pass's coarse steps
            (:func:`first_pass_steps`; ``times_s`` are then the samples of :func:`hold_samples`);
            ``ir0`` is then ignored.
        """
        ir = held_ir(radiosity.ir_of_emission(self.F, E), len(times_s), hold)
        if ir0 is not None and not hold:
            ir[0] = ir0
        a = radiosity.absorbed_flux(solar, ir, self.albedo, self.emissivity, self.solar_is_absorbed)
        with first_pass_steps(self.solver, hold):
            return conduct(self.solver, state, times_s, a, ir, prev, skip_K, self.emissivity)

    def ir_rows(self, T) -> np.ndarray:
        """The IR [W m-2] (n, nf) of surface temperature rows ``T`` (n, nf) [K]: one product."""
        return radiosity.ir_of_emission(self.F, radiosity.emitted(np.asarray(T, float), self.emissivity))

    def run_ir(self, state, times_s, solar, ir, active, T_last) -> Window:
        """Conduct the ``active`` columns [indices] over the window from ``state`` driven by the given IR
        rows ``ir`` (n, nf) [W m-2]; the others keep their surface temperatures ``T_last`` (n, nf) [K] and
        their state (a periodic start's skipped columns, :meth:`SpinUp.skip`)."""
        a = radiosity.absorbed_flux(solar, ir, self.albedo, self.emissivity, self.solar_is_absorbed)
        prev = Window(np.asarray(T_last, float), ir, np.asarray(state, float), np.zeros_like(self.solver.acc))
        return conduct(self.solver, state, times_s, a, ir, prev, 0.0, self.emissivity, active=active)


def skippable(converged, drift, t_min, tol_K: float) -> np.ndarray:
    """The columns a periodic start's next lagged pass need not run (the ``skip`` hook of
    :func:`thermal.periodic_state`, here and in :mod:`crater_thermal.simulate`): converged (bool (nf,)) and
    whose input IR has moved, since their last run, by ``drift`` [W m-2] (max over the samples) less than
    what could move them by :data:`SKIP_FRACTION` of ``tol_K`` [K], by the radiative bound
    ``|dT| <= |dIR| / (4 sigma T_min^3)`` (``t_min`` [K]: their coldest surface temperature of that run)."""
    bound = np.asarray(drift) / (4.0 * SIGMA * np.maximum(t_min, 1.0) ** 3)
    return np.asarray(converged, bool) & (bound <= SKIP_FRACTION * tol_K)


def held_ir(ir, n: int, hold: bool) -> np.ndarray:
    """The IR rows [W m-2] of a window of ``n`` samples: ``ir`` (n, m) itself, or with ``hold`` its one row
    (1, m) repeated over the n samples."""
    return np.repeat(ir[:1], n, axis=0) if hold else ir


def active_columns(ir, prev: Window, skip_K: float, emissivity: float) -> np.ndarray:
    """Columns [indices] whose temperatures may move by more than ``skip_K`` [K] from ``prev``'s when driven
    by the IR rows ``ir`` (n, m) [W m-2] instead of ``prev.ir``.

    A sustained change dQ of absorbed flux moves a column's surface temperature by at most
    dQ / (4 eps sigma T^3) (the radiative-equilibrium response; heat capacity and conduction only damp it),
    so a column whose ``eps |ir - prev.ir|`` stays below ``skip_K x 4 eps sigma min(T)^3`` over the window
    (``T`` its temperatures in ``prev``) is left out.
    """
    dq = emissivity * np.max(np.abs(ir - prev.ir), axis=0)
    tmin = np.min(prev.T, axis=0)
    return np.flatnonzero(dq > skip_K * 4.0 * emissivity * SIGMA * tmin**3)


def conduct(
    solver, state, times_s, a, ir, prev: Window | None, skip_K: float, emissivity: float, active=None
) -> Window:
    """Run ``solver``'s columns (all, or only the active ones against ``prev``) from ``state`` with absorbed
    flux rows ``a`` (n, m) [W m-2] driven by IR rows ``ir``; the :class:`Window` of all columns.
    ``active``: the columns to run [indices] (the others keep ``prev``'s results), instead of those of
    :func:`active_columns` with ``skip_K``."""
    solver.set_state(state)
    solver.reset_accumulators()
    if prev is None or (skip_K <= 0.0 and active is None) or (active is not None and len(active) == solver.ncol):
        T = solver.run_series(times_s, a, record=True)
        return Window(T, ir, solver.state(), solver.acc.copy())
    act = active_columns(ir, prev, skip_K, emissivity) if active is None else np.asarray(active)
    T, end, acc = prev.T.copy(), prev.end.copy(), prev.acc.copy()
    if act.size:
        T[:, act] = solver.run_columns(act, times_s, a[:, act])
        end[act] = solver.T[act]
        acc[act] = solver.acc[act]
    return Window(T, ir, end, acc, int(act.size))


def relax(
    columns, state, times_s, solar, ir0, emissivity: float, tol_K: float = DEFAULT_TOL_K, max_iter=MAX_ITERATIONS
):
    """The coupled pass over one window by waveform relaxation (module docstring).

    Parameters
    ----------
    columns : backend (:class:`LocalColumns` or the distributed one).
    state : (nf, nz) [K] at ``times_s[0]``.
    times_s, solar : the window's (n,) times [s] and (n, nf) sunlight rows [W m-2].
    ir0 : (nf,) IR [W m-2] at sample 0 (the one that ended the previous window), or None: ``F e(T0)``.
    emissivity : [-]
    tol_K : stop when no surface temperature changes by more than this between iterations [K].

    Returns
    -------
    (Window, iterations, last change [K])

    Raises
    ------
    SolverError
        Not converged in ``max_iter`` iterations.
    """
    own = getattr(columns, "relax_window", None)  # a backend that keeps the iterations where its columns are
    if own is not None:
        return own(state, times_s, solar, ir0, emissivity, tol_K, max_iter)
    T0 = np.asarray(state)[:, 0]
    E = np.broadcast_to(radiosity.emitted(T0, emissivity), (len(times_s), len(T0))).copy()
    prev = None
    change = np.inf
    for it in range(1, int(max_iter) + 1):
        w = columns.solve(state, times_s, solar, E, ir0, prev=prev, skip_K=SKIP_FRACTION * tol_K)
        if prev is not None:
            change = float(np.max(np.abs(w.T - prev.T)))
            if change <= tol_K:
                return w, it, change
        prev = w
        E = radiosity.emitted(np.asarray(w.T, float), emissivity)
    raise not_converged(max_iter, change, tol_K)


def not_converged(max_iter: int, change: float, tol_K: float) -> SolverError:
    """The error of a relaxation that did not converge in ``max_iter`` iterations (last change [K] > tol_K)."""
    return SolverError(
        f"waveform relaxation did not converge in {max_iter} iterations (last change {change:.3g} K > {tol_K} K); "
        "shorter windows converge faster"
    )


class SpinUp:
    """The start of the record by waveform relaxation: the periodic state over the spin-up window, each pass
    through it driven by the previous pass's emission (the lagged spin-up of :mod:`crater_thermal.simulate`:
    the same first pass, each facet's IR held :data:`FIRST_PASS_HOLD_S` at a time and stepped
    :data:`FIRST_PASS_STEP_S` at a time, :meth:`held`), or one relaxed pass (fixed spin-up, :meth:`coupled`).

    Parameters
    ----------
    columns : backend.
    solver : the ColumnSolver of all facets on this machine: holds the state between passes and gives
        ``thermal.periodic_state`` its Jacobian (the passes run in ``columns``).
    rows : ``rows(k0, k1)`` -> sunlight rows k0..k1-1 of the spin-up window [W m-2].
    store : segment store for the passes' temperature series (``wr_T0`` / ``wr_T1``) and ``spin_ir``.
    times_s : (ns,) the spin-up window's times [s]; block : samples per block (memory).
    emissivity : [-]; tol_K : relaxation tolerance of a :meth:`coupled` pass [K]; window : its window
    [samples].

    Backends with ``held_pass`` and ``lagged_pass`` (the dask one) run the periodic start's passes whole on
    their side; when one of those loses data (:class:`PassLost`), the pass is run again through
    ``columns.solve`` (a held pass: a fresh first pass; the periodic start's fixed point does not depend
    on it) and the later passes go through the store.

    Converged columns are skipped as in the local lagged start (:meth:`skip`, the ``skip`` hook of
    :func:`thermal.periodic_state`): between two passes the next pass's input IR is formed (``F e(T)`` of
    the pass's temperatures, into the store, or on the workers by ``next_inputs``), and a converged
    column whose input moved too little since its last run (:func:`skippable`) is not run; its last
    run's temperatures stand in the IR products. Backends without ``run_ir`` or ``next_inputs`` (and
    every pass after a lost one) run every column.
    """

    def __init__(self, columns, solver, rows, store, times_s, block, emissivity, tol_K, window, save_spin):
        self.columns, self.solver, self.rows, self.store = columns, solver, rows, store
        self.t, self.block, self.eps, self.tol, self.window, self.save_spin = (
            times_s,
            int(block),
            float(emissivity),
            float(tol_K),
            int(window),
            save_spin,
        )
        self.n = len(times_s)
        self.passes = 0
        self.iterations: list[int] = []  # relaxation iterations per window of a coupled pass
        self.holds = 0  # holds (one-vector products) of the held passes
        self.ir_end = None
        self.lag_in, self.lag_out = None, "wr_T0"
        self.remote_pass = False  # the latest pass ran on the backend and its series stayed there
        self.remote_lost = False  # a backend pass lost data once: later passes go through the store
        nf = solver.ncol
        self.periodic_tol = 0.0  # the periodic start's tolerance [K] (:meth:`periodic`)
        self.skipped = np.zeros(nf, bool)  # columns the next pass does not run
        self.drift = np.zeros(nf)  # max |input IR change| [W m-2] of each column since its last run
        self.t_min = np.full(nf, np.inf)  # coldest surface temperature [K] of each column's last run
        self.next_ready = False  # the next pass's input IR is formed ("wr_irn" or on the workers)
        #: columns run by each pass (diagnostics)
        self.columns_run: list[int] = []

    def coupled(self, on_step=None) -> None:
        """One relaxed pass from the solver's state (window by window to ``tol_K``); its temperatures kept as
        the next pass's input."""
        self.passes += 1
        self.columns_run.append(self.columns.n_facets)
        self.next_ready = False
        state = self.solver.state()
        ir = None
        acc = np.zeros_like(self.solver.acc)
        for w0 in range(0, self.n - 1, self.window):
            w1 = min(self.n - 1, w0 + self.window)
            win, it, _ = relax(self.columns, state, self.t[w0 : w1 + 1], self.rows(w0, w1 + 1), ir, self.eps, self.tol)
            self.iterations.append(it)
            self._keep(w0, win.T, win.ir, last=w1 == self.n - 1)
            self._keep_input(w0, win.ir, last=w1 == self.n - 1)
            state, ir, acc = win.end, win.ir[-1], acc + win.acc
            if on_step is not None:
                on_step(w1)
        self._finish(state, acc)

    def _blocks(self) -> list[tuple[int, int]]:
        """The passes' blocks ``(b0, b1)``: samples b0..b1, consecutive blocks sharing one."""
        return [(b0, min(self.n - 1, b0 + self.block)) for b0 in range(0, self.n - 1, self.block)]

    def held(self, on_step=None) -> None:
        """The first pass of a periodic start: every column conducted for :data:`FIRST_PASS_HOLD_S` with
        each facet's IR held at ``F e(T)`` of the temperatures at the hold's start, then one one-vector
        product of the emission reached gives the next hold's IR (:func:`hold_spans`, the same holds as
        :mod:`crater_thermal.simulate`'s lagged start), in steps of up to :data:`FIRST_PASS_STEP_S`
        (:func:`held_window`, on a cluster too); its temperatures are the next pass's input."""
        self.passes += 1
        self.columns_run.append(self.columns.n_facets)
        self.next_ready = False
        spans = [hold_spans(self.t, b0, b1) for b0, b1 in self._blocks()]
        if hasattr(self.columns, "held_pass") and not self.remote_lost:  # the pass on the workers
            try:
                state = self.solver.state()
                end, acc, self.ir_end = self.columns.held_pass(state, self.t, self.rows, self.block, on_step)
            except PassLost:  # data of the pass went with a worker: the pass through ``solve``
                self.remote_lost, self.remote_pass = True, False
            else:
                self.holds += sum(map(len, spans))
                self.remote_pass = True
                self.solver.set_state(end)
                self.solver.acc += acc
                self._swap()
                return
        state = self.solver.state()
        acc = np.zeros_like(self.solver.acc)
        surface = state[:, 0]
        for (b0, b1), holds in zip(self._blocks(), spans):
            sol = self.rows(b0, b1 + 1)
            T, ir = np.empty((b1 - b0 + 1, self.columns.n_facets)), np.empty((b1 - b0 + 1, self.columns.n_facets))
            for k, k1 in holds:
                E = radiosity.emitted(surface, self.eps)[None, :]
                solve = functools.partial(self.columns.solve, state, E=E, hold=True)
                win = held_window(solve, self.t[k : k1 + 1], sol[k - b0 : k1 - b0 + 1])
                T[k - b0 : k1 - b0 + 1], ir[k - b0 : k1 - b0 + 1] = win.T, win.ir
                state, acc, surface = win.end, acc + win.acc, np.asarray(win.T[-1], float)
            self.holds += len(holds)
            self._keep(b0, T, ir, last=b1 == self.n - 1)
            self._keep_input(b0, ir, last=b1 == self.n - 1)
            if on_step is not None:
                on_step(b1)
        self._finish(state, acc)

    def lagged(self, on_step=None) -> None:
        """One pass from the solver's state driven by the previous pass's emission (the first pass is
        :meth:`held`); the columns :meth:`skip` named are not run."""
        if self.lag_in is None:
            self.held(on_step)
            return
        self.passes += 1
        ready, self.next_ready = self.next_ready, False
        skipped = self.skipped if ready else np.zeros_like(self.skipped)
        self.columns_run.append(int(np.count_nonzero(~skipped)))
        if hasattr(self.columns, "lagged_pass") and not self.remote_lost:  # the pass on the workers
            try:
                end, acc, self.ir_end = self.columns.lagged_pass(
                    self.solver.state(),
                    self.t,
                    self.rows,
                    self.block,
                    lambda a, b: self.store.read(self.lag_in, a, b),
                    on_step,
                    skip=skipped if ready else None,
                )
            except PassLost:  # the previous pass's series went with a worker: a fresh first pass instead
                self.passes -= 1
                self.columns_run.pop()
                self.remote_lost, self.remote_pass = True, False
                self.held(on_step)
                return
            self.remote_pass = True
            self.solver.set_state(end)
            self.solver.acc += acc
            return
        state = self.solver.state()
        acc = np.zeros_like(self.solver.acc)
        run = np.flatnonzero(~skipped)
        for b0, b1 in self._blocks():
            T_last = self.store.read(self.lag_in, b0, b1 + 1)
            if ready:  # the input IR formed by :meth:`skip`
                ir = self.store.read("wr_irn", b0, b1 + 1)
                win = self.columns.run_ir(state, self.t[b0 : b1 + 1], self.rows(b0, b1 + 1), ir, run, T_last)
            else:
                E = radiosity.emitted(T_last, self.eps)
                win = self.columns.solve(state, self.t[b0 : b1 + 1], self.rows(b0, b1 + 1), E, None)
            self._keep(b0, win.T, win.ir, last=b1 == self.n - 1)
            self._keep_input(b0, win.ir, last=b1 == self.n - 1)
            state, acc = win.end, acc + win.acc
            if on_step is not None:
                on_step(b1)
        self._finish(state, acc)

    def _keep_input(self, k0, ir, last: bool) -> None:
        """Rows k0.. of the pass's input IR (``wr_irc``), for the drift of the next input (:meth:`skip`)."""
        if hasattr(self.columns, "run_ir"):
            self.store.write_rows("wr_irc", k0, np.asarray(ir[: len(ir) if last else len(ir) - 1]))

    def skip(self, converged) -> np.ndarray:
        """The ``skip`` hook of :func:`thermal.periodic_state`: forms the next pass's input IR and returns
        the converged columns that pass need not run (:func:`skippable`); none where the backend cannot
        (the class docstring)."""
        moved = self._next_inputs()
        if moved is None:
            self.skipped = np.zeros_like(self.skipped)
            return self.skipped
        dq, t_min = moved
        self.drift = np.where(self.skipped, self.drift, 0.0) + dq
        self.t_min = t_min
        self.next_ready = True
        self.skipped = skippable(converged, self.drift, self.t_min, self.periodic_tol)
        return self.skipped

    def _next_inputs(self):
        """Form the next pass's input IR from the latest pass's temperatures; returns (the largest change
        from the latest pass's input [W m-2], the coldest surface temperature [K]) per column, or None."""
        if self.remote_pass and not self.remote_lost:
            return self.columns.next_inputs() if hasattr(self.columns, "next_inputs") else None
        if self.remote_pass or not hasattr(self.columns, "run_ir") or self.lag_in is None:
            return None
        dq = np.zeros(self.columns.n_facets)
        t_min = np.full(self.columns.n_facets, np.inf)
        for b0, b1 in self._blocks():
            T = self.store.read(self.lag_in, b0, b1 + 1)
            ir = self.columns.ir_rows(T)
            np.maximum(dq, np.max(np.abs(ir - self.store.read("wr_irc", b0, b1 + 1)), axis=0), out=dq)
            np.minimum(t_min, np.min(T, axis=0), out=t_min)
            self.store.write_rows("wr_irn", b0, ir[: len(ir) if b1 == self.n - 1 else len(ir) - 1])
        return dq, t_min

    def _keep(self, k0, T, ir, last: bool) -> None:
        """Rows k0.. of the pass (the window's last row belongs to the next window, except at the end)."""
        n = len(T) if last else len(T) - 1
        self.store.write_rows(self.lag_out, k0, np.asarray(T[:n]))
        if self.save_spin:
            self.store.write_rows("spin_ir", k0, np.asarray(ir[:n]))
        if last:
            self.ir_end = np.asarray(ir[-1]).copy()

    def _finish(self, state, acc) -> None:
        self.solver.set_state(state)
        self.solver.acc += acc
        self._swap()

    def _swap(self) -> None:
        """The series just written is the next pass's input."""
        self.lag_in, self.lag_out = self.lag_out, ("wr_T1" if self.lag_out == "wr_T0" else "wr_T0")

    def periodic(self, tol_K: float, report=None) -> dict:
        """The periodic state (``thermal.periodic_state`` over lagged passes); the solver is left in it."""
        expected = 5

        def phi(x):
            self.solver.set_state(x)
            done0 = self.passes * (self.n - 1)
            total = max(expected, self.passes + 1) * (self.n - 1)
            self.lagged(None if report is None else (lambda k: report(done0 + k, total)))
            return self.solver.T.copy()

        self.periodic_tol = float(tol_K)
        info = thermal.periodic_state(self.solver, phi, tol_K=tol_K, anderson=False, skip=self.skip)
        if self.remote_pass:
            if self.save_spin:  # the IR the last pass ran with, from the backend
                for b0 in range(0, self.n, self.block):
                    b1 = min(self.n, b0 + self.block)
                    self.store.write_rows("spin_ir", b0, self.columns.pass_ir(b0, b1))
            self.columns.end_spinup()
        # the passes' own series: the record does not need them (a resumed run that starts the spin-up
        # again makes them again)
        self.store.drop("wr_T0", "wr_T1", "wr_irc", "wr_irn")
        return info
