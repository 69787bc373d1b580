"""Radiation exchange between facets: scattered sunlight and thermal infrared.

Notation (all per facet, irradiances in W m-2): ``F`` the view-factor matrix
(``F[i, j]`` = fraction of radiation leaving ``i`` that reaches ``j``;
irradiance on ``i`` from the exitance ``B`` of the others is ``(F @ B)_i``),
``A`` the albedo, ``E`` the direct solar irradiance.

* Scattered sunlight (Lambertian): the exitance satisfies ``B = A (E + F B)``,
  i.e. ``(I - A F) B = A E`` (exact radiosity), and the incident shortwave is
  ``Q = E + F B``. The thesis truncates the Neumann series after three
  reflections: ``Q = E + sum_{k=1..n} F (A F)^(k-1) A E``.
* Infrared: ``Q_ir = F @ (eps sigma T^4)``; infrared is not reflected (the
  thesis neglects it since ``1 - eps`` is small).
* Radiative equilibrium (no conduction): ``eps sigma T^4 = (1 - A) Q + eps Q_ir``,
  i.e. ``u = eps sigma T^4`` solves ``(I - eps F) u = (1 - A) Q``.

:func:`ingersoll_shadow_temperature` gives the analytic temperature in the
shadow of a spherical bowl (Ingersoll, Svitek & Murray 1992), with and without
infrared reflection.

In time (:class:`CoupledStepper`): every facet's conduction column advances one flux step at a time with
the IR it receives from the others' emission at the step's end, extrapolated from exact products (see
the class); the time loop that drives it is :mod:`crater_thermal.simulate`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from crater_thermal.choices import SCATTERING_METHODS
from crater_thermal.constants import ALBEDO, AU, EMISSIVITY, SIGMA, SOLAR_CONSTANT
from crater_thermal.errors import ConfigError, SolverError
from crater_thermal.vfoperator import SparseViewFactors, ViewFactorOperator, as_operator

# SCATTERING_METHODS ("exact", "bounces"), the methods for the scattered sunlight, is declared in
# crater_thermal.choices (the case schema's list) and re-exported here.
#: Thesis default number of reflections for the "bounces" method.
DEFAULT_BOUNCES = 3


#: Relative change (max norm) at which the iterative scattering solve stops. The error left is about the
#: last change times q / (1 - q), q = max(A rowsum) ~ 0.06-0.12 per product: ~1e-7 of the largest
#: exitance, a thousand times below the compressed operator's own product error (~1e-4). Measured on the
#: 12,800-facet topo81 terrain over two months: 2.4e-7 W m-2 from the 1e-9 solve (largest 1,114 W m-2),
#: 31 % fewer products.
ITERATIVE_RTOL = 1e-6
#: Iteration cap of the iterative solves.
ITERATIVE_MAX = 500
#: Right-hand sides per block of the iterative scattering solve (memory: a few (nf, k) arrays).
ITERATIVE_BLOCK = 64
#: Solves of the iterative scattering kept in flight with an asynchronous operator (a cluster's, whose
#: products run on the workers): while the workers make the others' products this process updates one.
#: 3 measured no faster than 2 on a 30k-facet year on 2 cores (the stage 27.1-30.5 s against 28.5-29.9 s;
#: bench/results/coupled_cluster_30k_solves3_vs2.json, docs/cluster.md).
ASYNC_SOLVES = 2

#: How the linear systems (scattered sunlight, radiative equilibrium) are solved: "auto" as a run does it,
#: by operator (:func:`resolve_solver`: direct with the exact matrix, iterative with the compressed
#: operator), "direct" (LU; the exact matrix only), "iterative" (fixed point / GMRES; any operator).
SOLVERS = ("auto", "direct", "iterative")
#: Relative residual at which the GMRES solve of the radiative equilibrium stops.
GMRES_RTOL = 1e-10

#: Above this fill fraction (and below DENSE_MAX_FACETS) linear systems are solved densely.
DENSE_FILL = 0.1
DENSE_MAX_FACETS = 8000


class _Factorised:
    """LU factorisation of ``I - diag(c) F``: dense LAPACK when F is dense-ish, else SuperLU."""

    def __init__(self, F: sp.csr_matrix, c: np.ndarray):
        nf = F.shape[0]
        self.dense = nf <= DENSE_MAX_FACETS and F.nnz > DENSE_FILL * nf * nf
        try:
            if self.dense:
                import scipy.linalg as sla

                M = -(c[:, None] * F.toarray())
                M[np.diag_indices(nf)] += 1.0
                self._lu = sla.lu_factor(M, check_finite=False)
                self._sla = sla
            else:
                M = sp.identity(nf, format="csc") - sp.diags(c) @ F
                self._lu = spla.splu(sp.csc_matrix(M))
        except MemoryError:
            # the sparse LU's fill-in grows far faster than F's non-zeros (30,752 facets: > 24 GB, issue 20)
            raise ConfigError(
                f"not enough memory for the direct (LU) solve of {nf} facets ({F.nnz} view factors); the "
                "iterative solver needs only a few vectors (steady: --solver iterative, or the compressed "
                "view-factor operator: --view-factors compressed)"
            ) from None

    @property
    def description(self) -> str:
        """How the system is solved, for a dataset attribute."""
        return "LU (dense LAPACK)" if self.dense else "LU (sparse SuperLU)"

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        if self.dense:
            return self._sla.lu_solve(self._lu, rhs, check_finite=False)
        return self._lu.solve(np.ascontiguousarray(rhs))


def _as_operator(F) -> ViewFactorOperator:
    """A view-factor operator from an operator, a sparse matrix or a dense array."""
    op = as_operator(F)
    if op.shape[0] != op.shape[1]:  # pragma: no cover - as_operator checks sparse input already
        raise ConfigError(f"view-factor matrix has shape {op.shape}; expected square (nf, nf)")
    return op


def _as_sparse(F) -> sp.csr_matrix:
    if isinstance(F, SparseViewFactors):
        return F.matrix
    if sp.issparse(F):
        F = sp.csr_matrix(F, dtype=float)
    else:
        F = np.asarray(F, dtype=float)
        if F.ndim != 2:
            raise ConfigError(f"view-factor matrix has shape {F.shape}; expected (nf, nf)")
        F = sp.csr_matrix(F)
    if F.shape[0] != F.shape[1]:
        raise ConfigError(f"view-factor matrix has shape {F.shape}; expected square (nf, nf)")
    return F


def operator_kind(F) -> str:
    """``"exact"`` for an exact view-factor matrix (sparse or dense), ``"compressed"`` for any other operator."""
    return "exact" if isinstance(_as_operator(F), SparseViewFactors) else "compressed"


def resolve_solver(solver: str, view_factors: str) -> str:
    """``"direct"`` or ``"iterative"``: how the linear systems are solved with a view-factor operator.

    Parameters
    ----------
    solver : {"auto", "direct", "iterative"}
        ``"auto"``: direct (LU) with the exact matrix, iterative with the compressed operator, as a run
        does (so the facet count that picks the operator, ``vfoperator.AUTO_COMPRESSED_MIN_FACETS``,
        picks the solver too).
    view_factors : {"exact", "compressed"}
        The operator's kind (a resolved ``vfoperator.resolve_method``, or :func:`operator_kind`).

    Raises
    ------
    ConfigError
        An unknown name, or ``"direct"`` with the compressed operator (it has no matrix to factorise).
    """
    if solver not in SOLVERS:
        raise ConfigError(f"solver = {solver!r}; allowed: {', '.join(SOLVERS)}")
    if view_factors not in ("exact", "compressed"):
        raise ConfigError(f"view-factor kind = {view_factors!r}; expected 'exact' or 'compressed'")
    if solver == "auto":
        return "direct" if view_factors == "exact" else "iterative"
    if solver == "direct" and view_factors == "compressed":
        raise ConfigError(
            "solver = 'direct' needs the exact view-factor matrix (the compressed operator has no matrix to "
            "factorise); use solver 'iterative' or exact view factors"
        )
    return solver


def check_per_facet(name: str, value, nf: int, lo: float, hi: float, hi_open: bool) -> np.ndarray:
    """``value`` (a scalar or (nf,)) as an (nf,) float array within [lo, hi] (or [lo, hi) if ``hi_open``);
    otherwise :class:`ConfigError` naming ``name``."""
    v = np.asarray(value, dtype=float)
    try:
        v = np.broadcast_to(v, (nf,)).copy()
    except ValueError:
        raise ConfigError(f"{name} has shape {np.shape(value)}; expected a scalar or ({nf},)") from None
    bad = ~np.isfinite(v) | (v < lo) | ((v >= hi) if hi_open else (v > hi))
    if np.any(bad):
        bracket = ")" if hi_open else "]"
        raise ConfigError(f"{name} = {float(v[bad][0])!r} is outside [{lo:g}, {hi:g}{bracket}")
    return v


class ScatteringSolver:
    """Direct + multiply scattered sunlight on every facet.

    Parameters
    ----------
    F : (nf, nf) sparse or dense float [-], or a vfoperator.ViewFactorOperator
        View factors.
    albedo : float or (nf,) float [-]
        Lambertian albedo, in [0, 1).
    method : {"exact", "bounces"}
        ``"exact"`` solves ``(I - A F) B = A E``: with an exact (sparse) matrix by LU, factorised once
        (dense LAPACK for dense-ish F, SuperLU otherwise); with a compressed operator iteratively, by
        the fixed point ``B <- A E + A F B`` (a contraction: ``A rowsum < 1``, the error shrinks by
        ``max(A rowsum)`` ~ 0.1 per product) until the largest change is below
        :data:`ITERATIVE_RTOL` of the largest exitance, many right-hand sides at once;
        ``"bounces"`` keeps ``n_bounces`` reflections (thesis: 3).
    n_bounces : int
        Number of reflections for ``"bounces"`` (>= 0; 0 = no scattering).
    solver : {"auto", "direct", "iterative"}
        How ``"exact"`` is solved (:func:`resolve_solver`): ``"auto"`` by the operator (LU for the exact
        matrix, the fixed point for the compressed operator, as above); ``"iterative"`` also runs the
        fixed point on an exact matrix (no factorisation: memory of a few vectors).
    """

    def __init__(self, F, albedo=ALBEDO, method: str = "exact", n_bounces: int = DEFAULT_BOUNCES, solver: str = "auto"):
        self.F = _as_operator(F)
        nf = self.F.shape[0]
        self.albedo = check_per_facet("albedo", albedo, nf, 0.0, 1.0, hi_open=True)
        if method not in SCATTERING_METHODS:
            raise ConfigError(f"scattering method = {method!r}; allowed: {', '.join(SCATTERING_METHODS)}")
        if isinstance(n_bounces, bool) or not isinstance(n_bounces, (int, np.integer)) or not 0 <= n_bounces <= 1000:
            raise ConfigError(f"n_bounces = {n_bounces!r} must be an integer in [0, 1000]")
        self.method = method
        self.n_bounces = int(n_bounces)
        #: "direct" or "iterative" (how ``"exact"`` is solved; see :func:`resolve_solver`)
        self.solver = resolve_solver(solver, operator_kind(self.F))
        self._lu = None
        #: iterations of the last iterative solve (0 for LU / bounces)
        self.iterations = 0
        if method == "exact" and nf and self.solver == "direct":
            self._lu = _Factorised(self.F.matrix, self.albedo)

    @property
    def description(self) -> str:
        """How the scattered sunlight was computed (after a solve), for a dataset attribute."""
        if self.method == "bounces":
            return f"{self.n_bounces} bounces"
        if self._lu is not None:
            return f"(I - A F) B = A E by {self._lu.description}"
        return (
            f"(I - A F) B = A E by the fixed point B <- A E + A F B to {ITERATIVE_RTOL:g} relative change "
            f"({self.iterations} products)"
        )

    @property
    def n_facets(self) -> int:
        return self.F.shape[0]

    def _fixed_point(self, rhs: np.ndarray, B0: np.ndarray | None):
        """Fixed point ``B <- rhs + A F B`` for rhs (nf, k), from B0 (default: rhs, the first bounce), as a
        generator: it yields each operand ``B`` whose product ``F B`` it needs and is sent that product
        (:meth:`_solved` makes them).

        Returns (as the generator's value) ``(B, FB)``: the last iterate and the product ``F B'`` of the
        one before it that formed it (``B = rhs + A FB`` exactly). ``FB`` differs from ``F B`` by at most
        the row sum times the last change (below :data:`ITERATIVE_RTOL` of the largest exitance), so it
        serves as the scattered irradiance without one more product. The update and its change are made
        in place (two (nf, k) arrays besides the product's), not in new temporaries."""
        a = self.albedo[:, None]
        B = rhs.copy() if B0 is None else np.array(B0, dtype=float).reshape(rhs.shape)
        Bn = np.empty_like(B)
        scale = max(float(np.abs(rhs).max()), np.finfo(float).tiny)
        for it in range(1, ITERATIVE_MAX + 1):
            FB = np.asarray((yield B)).reshape(rhs.shape)
            np.multiply(a, FB, out=Bn)
            Bn += rhs
            diff = np.subtract(Bn, B, out=B)  # B is not needed past this point: it holds the change
            change = max(float(diff.max()), -float(diff.min()))
            B, Bn = Bn, B
            if change <= ITERATIVE_RTOL * scale:
                self.iterations = max(self.iterations, it)
                return B, FB
        raise SolverError(
            f"scattered sunlight: the fixed-point solve did not converge in {ITERATIVE_MAX} "
            f"products (last change {change:.3g} W m-2)"
        )

    def _solved(self, problems) -> Iterator[tuple[int, tuple[np.ndarray, np.ndarray]]]:
        """``(i, (B, FB))`` of :meth:`_fixed_point` for each ``(rhs, B0)`` of ``problems`` (an iterable, read
        as the solves start), as each converges. With an :attr:`~ViewFactorOperator.asynchronous` operator
        (a cluster's) :data:`ASYNC_SOLVES` solves are in flight: the others' products run on the workers
        while this process updates one (the same operations per solve, so the same numbers); else one at a
        time."""
        width = ASYNC_SOLVES if self.F.asynchronous else 1
        problems = enumerate(problems)
        active: list = []  # (i, solve, its product in flight), oldest first

        def start() -> None:
            for i, (rhs, B0) in problems:
                solve = self._fixed_point(rhs, B0)
                active.append((i, solve, self.F.submit(next(solve))))
                return

        for _ in range(width):
            start()
        while active:
            i, solve, product = active.pop(0)
            try:
                operand = solve.send(product.result())
            except StopIteration as done:
                yield i, done.value
                start()
            else:
                active.append((i, solve, self.F.submit(operand)))

    def exitance(self, E_direct: np.ndarray, B0: np.ndarray | None = None) -> np.ndarray:
        """Reflected shortwave exitance ``B`` [W m-2], same shape as ``E_direct`` ((nt, nf) or (nf,)).

        ``B0`` (same shape): starting guess of the iterative solve (compressed operator only), e.g. the
        previous step's exitance; ignored by the LU and bounce methods.
        """
        E = self._checked(E_direct)
        if self.n_facets == 0:
            return np.zeros_like(E)
        if self.method == "exact" and self._lu is None:
            B = np.zeros_like(E)
            for rows, Bb, _ in self._blocks(E, B0):
                B.reshape(-1, self.n_facets)[rows] = Bb.T
            return B
        return self._exitance(E)

    def _checked(self, E_direct) -> np.ndarray:
        E = np.asarray(E_direct, dtype=float)
        if E.shape[-1] != self.n_facets or E.ndim not in (1, 2):
            raise ConfigError(f"E_direct has shape {E.shape}; expected ({self.n_facets},) or (nt, {self.n_facets})")
        return E

    def _blocks(self, E: np.ndarray, B0: np.ndarray | None) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The iterative solve of E (nf,) or (nt, nf) in blocks of :data:`ITERATIVE_BLOCK` samples: yields
        ``(rows, B, FB)``, the rows (samples) of a block and their exitance and scattered irradiance
        (nf, k), as each block converges (:meth:`_solved`). Samples without sunlight on any facet that
        reflects (night over the whole mesh) have ``B = 0`` exactly and are not yielded."""
        self.iterations = 0
        E2 = E.reshape(-1, self.n_facets)
        G = None if B0 is None else np.asarray(B0, dtype=float).reshape(E2.shape)
        reflects = self.albedo != 0.0
        lit_any = E2 != 0.0 if reflects.all() else (E2 != 0.0) & reflects
        lit = np.flatnonzero(np.any(lit_any, axis=1))
        blocks = [lit[c : c + ITERATIVE_BLOCK] for c in range(0, len(lit), ITERATIVE_BLOCK)]
        problems = (
            (np.ascontiguousarray((E2[rows] * self.albedo).T), None if G is None else np.ascontiguousarray(G[rows].T))
            for rows in blocks
        )
        for i, (B, FB) in self._solved(problems):
            yield blocks[i], B, FB

    def _exitance(self, E: np.ndarray) -> np.ndarray:
        """Exitance by LU or by bounces (E checked, (nf,) or (nt, nf)); same shape back."""
        rhs = (self.albedo * E).T  # (nf,) or (nf, nt)
        if self.method == "exact":
            return np.asarray(self._lu.solve(rhs)).T
        # B = sum_{k=0}^{n-1} (A F)^k A E   (n reflections in total)
        B = np.zeros_like(rhs)
        term = rhs
        for k in range(self.n_bounces):
            B = B + term
            if k + 1 < self.n_bounces:
                term = self.F.matvec(term) * (self.albedo if rhs.ndim == 1 else self.albedo[:, None])
        return np.asarray(B).T

    def solar_incident(self, E_direct: np.ndarray) -> np.ndarray:
        """Direct + scattered shortwave irradiance [W m-2].

        Parameters
        ----------
        E_direct : (nf,) or (nt, nf) float [W m-2]

        Returns
        -------
        Q : same shape as ``E_direct`` [W m-2]; ``Q = E + max(F B, 0)``. The scattered part is
            non-negative physically; the compressed operator's low-rank far field can return round-off
            negatives (about 1e-3 of the largest term) where a facet sees no lit terrain, so it is clipped
            at zero (a run's flux file refuses negative irradiance).
        """
        E = self._checked(E_direct)
        Q = E.copy()
        if self.n_facets == 0:
            return Q
        if self.method == "exact" and self._lu is None:
            # the iterative solve's last product is the scattered irradiance (see _fixed_point)
            Q2 = Q.reshape(-1, self.n_facets)
            for rows, _, FB in self._blocks(E, None):
                Q2[rows] += np.maximum(FB.T, 0.0)
            return Q
        B = self._exitance(E)
        if E.ndim == 1:
            return Q + np.maximum(np.asarray(self.F.matvec(B)), 0.0)
        lit = np.flatnonzero(np.any(B != 0.0, axis=1))  # rows with no exitance anywhere scatter nothing
        if len(lit):
            Q[lit] += np.maximum(np.asarray(self.F.matvec(np.ascontiguousarray(B[lit].T))).T, 0.0)
        return Q


def ir_incident(F, T: np.ndarray, emissivity=EMISSIVITY) -> np.ndarray:
    """Infrared irradiance from the rest of the terrain, ``F @ (eps sigma T^4)``.

    Parameters
    ----------
    F : (nf, nf) sparse or dense [-], or a vfoperator.ViewFactorOperator
    T : (..., nf) float [K]
    emissivity : float or (nf,) float [-]

    Returns
    -------
    (..., nf) float [W m-2]
    """
    F = _as_operator(F)
    T = np.asarray(T, dtype=float)
    nf = F.shape[0]
    if T.shape[-1] != nf:
        raise ConfigError(f"temperature has shape {T.shape}; last axis must be {nf} facets")
    eps = check_per_facet("emissivity", emissivity, nf, 0.0, 1.0, hi_open=False)
    u = eps * SIGMA * T**4
    flat = u.reshape(-1, nf)
    # >= 0 physically; clipped for the compressed operator's round-off (see solar_incident)
    return np.maximum(np.asarray(F.matvec(np.ascontiguousarray(flat.T))).T.reshape(T.shape), 0.0)


def equilibrium_temperature(
    F, solar_incident: np.ndarray, albedo=ALBEDO, emissivity=EMISSIVITY, solver: str = "auto"
) -> np.ndarray:
    """Radiative-equilibrium surface temperature (no conduction) [K].

    Solves ``(I - eps F) u = (1 - A) Q`` for ``u = eps sigma T^4``: directly (LU) with an exact matrix,
    by GMRES (relative residual :data:`GMRES_RTOL`) with a compressed operator (``solver="auto"``, see
    :func:`resolve_solver`; ``"iterative"`` runs GMRES on an exact matrix too).

    Parameters
    ----------
    F : (nf, nf) view factors [-] (matrix or vfoperator.ViewFactorOperator)
    solar_incident : (nf,) float [W m-2]
    albedo, emissivity : float or (nf,) float [-]
    solver : {"auto", "direct", "iterative"}

    Returns
    -------
    T : (nf,) float [K]
    """
    return _equilibrium(F, solar_incident, albedo, emissivity, solver)[0]


def _equilibrium(F, solar_incident, albedo, emissivity, solver: str) -> tuple[np.ndarray, str]:
    """:func:`equilibrium_temperature` and how it was solved (a dataset attribute's text)."""
    op = _as_operator(F)
    nf = op.shape[0]
    A = check_per_facet("albedo", albedo, nf, 0.0, 1.0, hi_open=True)
    eps = check_per_facet("emissivity", emissivity, nf, 0.0, 1.0, hi_open=False)
    if np.any(eps <= 0):
        raise ConfigError("emissivity = 0 is outside (0, 1] for a radiative equilibrium")
    kind = resolve_solver(solver, operator_kind(op))
    Q = np.asarray(solar_incident, dtype=float)
    rhs = (1.0 - A) * Q
    if kind == "direct":
        lu = _Factorised(op.matrix, eps)
        u, how = lu.solve(rhs), f"(I - eps F) u = (1 - A) Q by {lu.description}"
    else:
        products = [0]

        def matvec(x):
            products[0] += 1
            return x - eps * op.matvec(np.ravel(x))

        M = spla.LinearOperator((nf, nf), matvec=matvec, dtype=float)
        u, info = spla.gmres(M, rhs, x0=rhs, rtol=GMRES_RTOL, atol=0.0, restart=50, maxiter=ITERATIVE_MAX)
        if info != 0:
            raise SolverError(f"radiative equilibrium: GMRES did not converge (info {info})")
        how = f"(I - eps F) u = (1 - A) Q by GMRES to relative residual {GMRES_RTOL:g} ({products[0]} products)"
    u = np.maximum(u, 0.0)  # round-off only: every term is non-negative
    return (u / (eps * SIGMA)) ** 0.25, how


def steady_state(
    mesh,
    F,
    tracer,
    sun_dir,
    sun_distance_m: float = AU,
    albedo=ALBEDO,
    emissivity=EMISSIVITY,
    solar_constant: float = SOLAR_CONSTANT,
    disk=None,
    method: str = "exact",
    n_bounces: int = DEFAULT_BOUNCES,
    solver: str = "auto",
) -> dict:
    """Radiative equilibrium of a crater under a fixed Sun (no conduction).

    Parameters
    ----------
    mesh : geometry.Mesh
    F : (nf, nf) view factors [-], or a vfoperator.ViewFactorOperator (exact or compressed)
    tracer : raytrace.RayTracer
    sun_dir : (3,) float [unit]
        Direction toward the Sun (crater frame: x east, y north, z up).
    sun_distance_m : float [m]
    albedo, emissivity : float or (nf,) [-]
    solar_constant : float [W m-2] at 1 au
    disk : illumination.SunDisk or None
        ``None`` = point Sun.
    method, n_bounces :
        Scattering method (see :class:`ScatteringSolver`).
    solver : {"auto", "direct", "iterative"}
        How the scattering and the equilibrium systems are solved (:func:`resolve_solver`).

    Returns
    -------
    dict of (nf,) float arrays: ``surface_temperature`` [K], ``solar_direct``,
    ``solar_incident``, ``ir_incident`` [W m-2].
    """
    return steady_solution(
        mesh, F, tracer, sun_dir, sun_distance_m, albedo, emissivity, solar_constant, disk, method, n_bounces, solver
    )[0]


def steady_solution(
    mesh,
    F,
    tracer,
    sun_dir,
    sun_distance_m: float = AU,
    albedo=ALBEDO,
    emissivity=EMISSIVITY,
    solar_constant: float = SOLAR_CONSTANT,
    disk=None,
    method: str = "exact",
    n_bounces: int = DEFAULT_BOUNCES,
    solver: str = "auto",
) -> tuple[dict, dict]:
    """:func:`steady_state` (same parameters) and how it was solved.

    Returns
    -------
    results : dict
        As :func:`steady_state`.
    methods : dict of str
        ``solver`` ("direct" or "iterative"), ``scattering_solve`` and ``ir_solve`` (the system each
        solved and how, with the number of operator products of an iterative solve).
    """
    from crater_thermal.illumination import direct_irradiance

    s = np.asarray(sun_dir, dtype=float).reshape(1, 3)
    E = direct_irradiance(mesh, tracer, s, np.array([float(sun_distance_m)]), solar_constant, disk=disk)[0]
    scat = ScatteringSolver(F, albedo, method=method, n_bounces=n_bounces, solver=solver)
    Q = scat.solar_incident(E)
    T, ir_how = _equilibrium(F, Q, albedo, emissivity, scat.solver)
    results = {
        "surface_temperature": T,
        "solar_direct": E,
        "solar_incident": Q,
        "ir_incident": ir_incident(F, T, emissivity),
    }
    return results, {"solver": scat.solver, "scattering_solve": scat.description, "ir_solve": ir_how}


# --------------------------------------------------------------------- Ingersoll bowl


def bowl_view_factor(depth_to_diameter: float) -> float:
    """View factor ``f = 4 gamma^2 / (1 + 4 gamma^2)`` of a spherical bowl onto itself [-]."""
    g = float(depth_to_diameter)
    return 4.0 * g * g / (1.0 + 4.0 * g * g)


def ingersoll_shadow_temperature(
    elevation_rad: float,
    depth_to_diameter: float,
    albedo: float,
    emissivity: float,
    solar_flux: float,
    ir_reflection: bool = False,
) -> float:
    """Radiative-equilibrium temperature in the shadow of a spherical bowl [K].

    Parameters
    ----------
    elevation_rad : float [rad]
        Sun elevation above the horizontal (shadows exist while it is below the
        bowl's rim slope).
    depth_to_diameter : float [-]
    albedo, emissivity : float [-]
    solar_flux : float [W m-2]
    ir_reflection : bool
        ``True``: Ingersoll et al. (1992) Eq. 8, which reflects infrared inside
        the bowl: ``sigma T^4 = S sin e f (1 - A)/(1 - A f) [1 + A (1 - f)/eps]``.
        ``False`` (this model, no infrared reflection): the exact bowl solution
        ``eps sigma T^4 = (1 - A) f E_d /(1 - A f) [A + eps/(1 - eps f)]`` with
        ``E_d = S sin e (1 - f)`` the bowl-mean direct flux.
    """
    f = bowl_view_factor(depth_to_diameter)
    A, eps, S = float(albedo), float(emissivity), float(solar_flux)
    if ir_reflection:
        sT4 = S * np.sin(elevation_rad) * f * (1 - A) / (1 - A * f) * (1 + A * (1 - f) / eps)
    else:
        Ed = S * np.sin(elevation_rad) * (1 - f)
        sT4 = (1 - A) * f * Ed / (1 - A * f) * (A + eps / (1 - eps * f)) / eps
    return float((sT4 / SIGMA) ** 0.25)


# ----------------------------------------------------------------------------- IR exchange in time: the coupled step


def emitted(T: np.ndarray, emissivity: float) -> np.ndarray:
    """Emitted flux eps sigma T^4 [W m-2]."""
    return emissivity * SIGMA * T**4


def absorbed_flux(solar, ir, albedo: float, emissivity: float, solar_is_absorbed: bool = False) -> np.ndarray:
    """Absorbed flux [W m-2] of sunlight [W m-2] (incident, or already absorbed when ``solar_is_absorbed``:
    an incidence-dependent albedo) and incident IR [W m-2]: ``(1 - albedo) solar + eps ir``."""
    if solar_is_absorbed:
        return solar + emissivity * ir
    return (1.0 - albedo) * solar + emissivity * ir


def ir_of_emission(F, E_rows: np.ndarray) -> np.ndarray:
    """IR irradiance [W m-2] (n, nf) from emitted-flux rows ``E_rows`` (n, nf) [W m-2]: one product with
    ``F`` for all rows, clipped at 0 (a compressed operator may leave round-off of either sign where
    nothing is seen); zero without an operator."""
    if F is None:
        return np.zeros_like(E_rows)
    return np.maximum(np.asarray(F @ np.ascontiguousarray(np.asarray(E_rows, float).T)).T, 0.0)


def prompt_ir(solar, direct, albedo: float) -> np.ndarray:
    """The IR [W m-2] that the terrain's instant re-emission of the sunlight it absorbs adds on each facet:
    ``(1 - A) / A`` times the scattered sunlight ``solar - direct`` [W m-2] (same shapes).

    The scattered sunlight on a facet is ``F (A S)`` for the shortwave ``S`` reaching the terrain it sees
    (direct and scattered, albedo ``A``); a surface in radiative equilibrium would emit ``(1 - A) S`` of it,
    whose IR on the facet is ``F ((1 - A) S)``: the same field times ``(1 - A) / A``. The coupled steps of
    :meth:`CoupledStepper.steps` extrapolate the IR less this part and add it back, so that the IR's kinks
    at sunrise and sunset on the terrain a facet sees, which this part carries, are not extrapolated.
    Zero for ``A = 0`` (nothing scattered)."""
    albedo = float(albedo)
    if albedo <= 0.0:
        return np.zeros(np.shape(solar))
    return (1.0 - albedo) / albedo * np.maximum(np.asarray(solar, float) - np.asarray(direct, float), 0.0)


def implicit_run(stepper, times_s, solar, iterations: int = 10) -> np.ndarray:
    """The fully implicit exchange, the reference of the coupled schemes: every step's end IR iterated to
    the fixed point ``ir1 = F e(T1(ir1))`` (``iterations`` conduction solves of the step, then the step
    with the last IR), from ``stepper``'s solver state (at ``times_s[0]``).

    Parameters
    ----------
    stepper : :class:`CoupledStepper` (its solver, operator, albedo and emissivity).
    times_s : (nt,) [s]
    solar : (nt, nf) sunlight rows [W m-2] (as :meth:`CoupledStepper.step`).

    Returns
    -------
    (nt, nf) surface temperature [K] (first row: the start).
    """
    solver = stepper.solver
    T = np.empty((len(times_s), np.shape(solar)[1]))
    T[0] = solver.surface_temperature
    ir = stepper.ir(T[0])
    for k in range(len(times_s) - 1):
        dt = times_s[k + 1] - times_s[k]
        a_k = stepper.absorbed(solar[k], ir)
        start = solver.state()
        ir1 = ir
        for _ in range(iterations):
            solver.advance(a_k, stepper.absorbed(solar[k + 1], ir1), dt)
            ir1 = stepper.ir(solver.surface_temperature)
            solver.set_state(start)
        T[k + 1] = solver.advance(a_k, stepper.absorbed(solar[k + 1], ir1), dt)
        ir = ir1
    return T


#: The extrapolated IR scheme's acceptance test: a column whose absorbed IR at the end of the step differs
#: from that of the new temperatures by more than max(IR_DEFECT_W_M2, IR_DEFECT_REL x its absorbed flux)
#: takes the step again driven by the new temperatures' IR (CoupledStepper).
IR_DEFECT_W_M2 = 0.01
IR_DEFECT_REL = 1e-3
#: :meth:`CoupledStepper.steps` (several samples per IR product) also takes a group again where the miss
#: would move the surface by more than this [K] in radiative balance (cold shadowed facets).
GROUP_DEFECT_K = 0.005


@dataclass
class CoupledStepper:
    """Advance every facet's column one flux step at a time, with IR exchange between facets.

    Within a step the absorbed flux varies linearly between its values at the two samples; the IR part
    at the step's end depends on the temperatures being computed. Two ways to get it
    (``ir_scheme``, ``[steps] ir_coupling``):

    * ``"extrapolated"`` (default): the IR at the end of the step is extrapolated linearly in time from
      the exact IR products F·e(T) at the two previous samples (clipped at 0); after the step the exact
      product of the new temperatures is formed for the next extrapolation. One conduction solve and one
      IR product per step. The extrapolation error is second order in the step (O(dt² d²IR/dt²)), does
      not accumulate (every extrapolation is built from exact products), and the scheme is stable for
      any view-factor row sum ≤ 1 (the error recurrence has roots of modulus √g, g < 1 the facet's
      radiative gain). The first step of a sequence (no history yet) is a predictor-corrector step.
    * ``"predictor"``: predictor-corrector: a predictor solve with the start-of-step IR held, the IR
      product of its end temperatures, a corrector solve from the same start with that IR at the end.
      Two conduction solves and one IR product per step.

    Either way the IR returned for the end of the step is the one that drove it, so a replay of the
    recorded series reproduces the run. :meth:`steps` takes several samples per IR product
    (``[steps] ir_product_samples``, the record's default from 10,000 facets).

    Parameters
    ----------
    solver : thermal.ColumnSolver with one column per facet.
    F : vfoperator.ViewFactorOperator (or a sparse (nf, nf) matrix), or None for no exchange (flat ground).
    albedo, emissivity : [-]
    solar_is_absorbed : the sunlight rows handed to :meth:`step` are already the absorbed sunlight
        [W m-2] (an incidence-dependent albedo, ``[surface] albedo_model``), not the incident one.
    ir_scheme : "extrapolated" | "predictor" (above).
    """

    solver: object
    F: object
    albedo: float
    emissivity: float
    solar_is_absorbed: bool = False
    ir_scheme: str = "extrapolated"
    #: (surface T [K] the history belongs to, F·e(T) at it, F·e(T) one sample before, that step [s])
    _history: tuple | None = field(default=None, repr=False)
    #: (prompt IR at the history's two samples) of :meth:`steps`, or None
    _prompt: tuple | None = field(default=None, repr=False)
    #: column-steps taken by extrapolation, and those taken again (diagnostics)
    stepped: int = 0
    redone: int = 0

    def ir(self, T_surface: np.ndarray) -> np.ndarray:
        """IR irradiance [W m-2] on every facet from the others' emission."""
        if self.F is None:
            return np.zeros_like(T_surface)
        ir = np.asarray(self.F @ emitted(T_surface, self.emissivity)).reshape(np.shape(T_surface))
        # a compressed operator may leave round-off of either sign (~tolerance) where nothing is seen
        return np.maximum(ir, 0.0)

    def ir_rows(self, T_rows: np.ndarray) -> np.ndarray:
        """IR irradiance [W m-2] (n, nf) of surface temperatures (n, nf): one product for all rows."""
        return ir_of_emission(self.F, emitted(np.asarray(T_rows, float), self.emissivity))

    def absorbed(self, solar: np.ndarray, ir: np.ndarray) -> np.ndarray:
        """Absorbed flux [W m-2] of sunlight rows (incident, or absorbed when ``solar_is_absorbed``) and IR."""
        return absorbed_flux(solar, ir, self.albedo, self.emissivity, self.solar_is_absorbed)

    # -- the extrapolation history (explicit, so that checkpoints can carry it)
    def reset_history(self) -> None:
        """Forget the IR history: the next step is a predictor-corrector step (a new sequence)."""
        self._history = None
        self._prompt = None

    def history(self) -> dict | None:
        """The IR history for a checkpoint: ``{"ir_now", "ir_before", "dt_before"}`` (and, after
        :meth:`steps`, ``"prompt_now"``, ``"prompt_before"``) or None."""
        if self._history is None or not self._history_valid():
            return None
        _, now, before, dt = self._history
        h = {"ir_now": now.copy(), "ir_before": before.copy(), "dt_before": float(dt)}
        if self._prompt is not None:
            h["prompt_now"], h["prompt_before"] = (p.copy() for p in self._prompt)
        return h

    def set_history(self, h: dict | None) -> None:
        """Restore :meth:`history` (after the solver's state is restored from the same checkpoint)."""
        if h is None:
            self._history = self._prompt = None
            return
        self._prompt = None
        if "prompt_now" in h:
            self._prompt = (np.asarray(h["prompt_now"], float).copy(), np.asarray(h["prompt_before"], float).copy())
        self._history = (
            self.solver.surface_temperature,
            np.asarray(h["ir_now"], float).copy(),
            np.asarray(h["ir_before"], float).copy(),
            float(h["dt_before"]),
        )

    def _history_valid(self) -> bool:
        # valid only for the very state it was made at (a restored or reset state starts a new sequence)
        T = self._history[0]
        return np.array_equal(T, self.solver.T[:, 0])

    def step(self, solar_k, solar_k1, ir_k, duration_s):
        """One coupled step. Returns ``(T_surface_k1, ir_k1)``: ``ir_k1`` [W m-2] is the IR that drove
        the step's end (pass it back as ``ir_k`` of the next step)."""
        a_k = self.absorbed(solar_k, ir_k)
        if self.F is None:
            T1 = self.solver.advance(a_k, self.absorbed(solar_k1, ir_k), duration_s)
            return T1, ir_k
        if self.ir_scheme == "extrapolated" and self._history is not None and self._history_valid():
            _, now, before, dt_before = self._history
            ir_k1 = np.maximum(now + (now - before) * (duration_s / dt_before), 0.0)
            start = self.solver.snapshot()  # a reused buffer: only the redo below reads it
            a_k1 = self.absorbed(solar_k1, ir_k1)
            T1 = self.solver.advance(a_k, a_k1, duration_s)
            exact = self.ir(T1)
            # where the extrapolation missed the IR of the new temperatures (sunrise or sunset on the
            # terrain a facet sees), those columns take the step again driven by that IR
            miss = np.flatnonzero(
                self.emissivity * np.abs(exact - ir_k1) > np.maximum(IR_DEFECT_W_M2, IR_DEFECT_REL * np.abs(a_k1))
            )
            if miss.size:
                ir_k1[miss] = exact[miss]
                T1[miss] = self.solver.redo_columns(
                    miss, start, a_k[miss], self.absorbed(solar_k1[miss], ir_k1[miss]), duration_s
                )
            self._history = (T1, exact, now, float(duration_s))
            self.redone += miss.size
            self.stepped += T1.size
            return T1, ir_k1
        now = self.ir(self.solver.T[:, 0]) if self.ir_scheme == "extrapolated" else None
        start = self.solver.state()
        T_pred = self.solver.advance(a_k, self.absorbed(solar_k1, ir_k), duration_s)
        ir_k1 = self.ir(T_pred)
        self.solver.set_state(start)
        T1 = self.solver.advance(a_k, self.absorbed(solar_k1, ir_k1), duration_s)
        if now is not None:
            self._history = (T1, self.ir(T1), now, float(duration_s))
        return T1, ir_k1

    def steps(self, times_s, solar_rows, ir_k, prompt=None):
        """Several coupled steps with one IR product (the extrapolated scheme; ``[steps]
        ir_product_samples``): through the samples of ``times_s`` (m + 1 of them, the first the solver's
        current state).

        The IR of every sample of the group is predicted from the last two exact products, linearly in
        time, after taking out of them the part that follows the sunlight at once (``prompt``: the IR that
        the terrain's instant re-emission of the sunlight it absorbs adds, :func:`prompt_ir`), which is
        added back at each sample: the kink of the IR at sunrise and sunset on the terrain a facet sees is
        in ``prompt``, not in what is extrapolated. The columns run through the group in one solve; the
        exact IR of the group's end is formed, and a column whose IR the prediction missed (at the end, or
        between, against the exact end's IR interpolated the same way and kept within the IR of the group's
        two ends) by more than :meth:`_group_defect` (the single step's :data:`IR_DEFECT_W_M2` /
        :data:`IR_DEFECT_REL`, capped by :data:`GROUP_DEFECT_K`) takes the group again, driven by that
        interpolated IR.

        Parameters
        ----------
        times_s : (m + 1,) [s]
        solar_rows : (m + 1, nf) sunlight of the samples [W m-2] (as :meth:`step`).
        ir_k : (nf,) the IR that drove the current sample [W m-2].
        prompt : (m + 1, nf) [W m-2] or None (zero).

        Returns
        -------
        ``(T (m, nf), ir (m, nf))``: surface temperature [K] and the IR [W m-2] that drove each sample after
        the first (pass ``ir[-1]`` back as ``ir_k``). With one step, another scheme or no history yet the
        samples are taken one :meth:`step` at a time.
        """
        times_s = np.asarray(times_s, float)
        m = len(times_s) - 1
        nf = len(ir_k)
        if m < 1:
            raise ConfigError("CoupledStepper.steps: need at least two samples")
        P = np.zeros((m + 1, nf)) if prompt is None else np.asarray(prompt, float)
        if self.F is None or self.ir_scheme != "extrapolated" or self._history is None or not self._history_valid():
            Ts, irs = np.empty((m, nf)), np.empty((m, nf))
            for q in range(m):
                Ts[q], ir_k = self.step(solar_rows[q], solar_rows[q + 1], ir_k, times_s[q + 1] - times_s[q])
                irs[q] = ir_k
            self._prompt = (P[-1].copy(), P[-2].copy())
            return Ts, irs
        _, now, before, dt_before = self._history
        p_now, p_before = self._prompt if self._prompt is not None else (P[0], P[0])
        tau = times_s[1:] - times_s[0]
        r_now = now - p_now
        ir = np.maximum(r_now + (r_now - (before - p_before)) * (tau / dt_before)[:, None] + P[1:], 0.0)
        start = self.solver.snapshot()
        a = np.empty((m + 1, nf))
        a[0] = self.absorbed(solar_rows[0], ir_k)
        a[1:] = self.absorbed(solar_rows[1:], ir)
        T = self.solver.run_series(times_s, a, record=True)[1:]
        exact = self.ir(T[-1])
        # the IR between, from ir_k to the exact end: linear in time less the prompt part, which is added back
        w = (tau[:-1] / tau[-1])[:, None]
        r0 = ir_k - P[0]
        between = r0 + (exact - P[-1] - r0) * w + P[1:-1]
        # ... kept within the IR of the group's two ends: where the terrain is just lit, its prompt part
        # outruns the IR (the lit surface has not warmed yet) and the interpolation would dip below both
        np.clip(between, np.minimum(ir_k, exact), np.maximum(ir_k, exact), out=between)
        bad = self.emissivity * np.abs(exact - ir[-1]) > self._group_defect(a[-1], T[-1])
        bad |= np.any(self.emissivity * np.abs(between - ir[:-1]) > self._group_defect(a[1:-1], T[:-1]), axis=0)
        miss = np.flatnonzero(bad)
        if miss.size:
            ir[:-1, miss] = between[:, miss]
            ir[-1, miss] = exact[miss]
            am = np.empty((m + 1, miss.size))
            am[0] = a[0, miss]
            am[1:] = self.absorbed(solar_rows[1:, miss], ir[:, miss])
            T[:, miss] = self.solver.rerun_columns(miss, start, times_s, am)[1:]
        self._history = (self.solver.T[:, 0].copy(), exact, now, float(tau[-1]))
        self._prompt = (P[-1].copy(), p_now.copy())
        self.redone += miss.size * m
        self.stepped += T.size
        return T, ir

    def _group_defect(self, absorbed, T):
        """The absorbed-IR miss [W m-2] above which a column takes a group of :meth:`steps` again: the single
        step's threshold, but never more than what would move a surface at ``T`` [K] by
        :data:`GROUP_DEFECT_K` in radiative balance (``4 eps sigma T^3 GROUP_DEFECT_K``: 7e-5 W m-2 at 40 K)."""
        thr = np.maximum(IR_DEFECT_W_M2, IR_DEFECT_REL * np.abs(absorbed))
        return np.minimum(thr, 4.0 * self.emissivity * SIGMA * np.asarray(T, float) ** 3 * GROUP_DEFECT_K)

    def run(
        self,
        times_s: np.ndarray,
        solar: np.ndarray,
        ir0: np.ndarray | None = None,
        record: bool = True,
        on_step: Callable | None = None,
        first_step: int = 0,
        product_samples: int = 1,
        prompt: np.ndarray | None = None,
    ):
        """Run over all samples from the solver's current state (at ``times_s[first_step]``).

        ``product_samples`` > 1: the samples taken that many at a time by :meth:`steps` (one IR product
        each; ``prompt`` (nt, nf) [W m-2], :func:`prompt_ir`, or None for zero), as the record of a run
        with ``[steps] ir_product_samples`` takes them; 1: one :meth:`step` per sample.

        Returns ``(T_surface (nt, nf), ir (nt, nf))`` when ``record``; else ``(None, ir_last)``.
        """
        nt, nf = solar.shape
        T = self.solver.surface_temperature.copy()
        ir = self.ir(T) if ir0 is None else ir0
        out_T = out_ir = None
        if record:
            out_T = np.empty((nt, nf))
            out_ir = np.empty((nt, nf))
            out_T[first_step] = T
            out_ir[first_step] = ir
        g = int(product_samples)
        k = first_step
        while k < nt - 1:
            e = min(k + g, nt - 1)
            if g == 1:
                T, ir = self.step(solar[k], solar[k + 1], ir, times_s[k + 1] - times_s[k])
                Ts, irs = T[None, :], ir[None, :]
            else:
                Ts, irs = self.steps(
                    times_s[k : e + 1], solar[k : e + 1], ir, None if prompt is None else prompt[k : e + 1]
                )
                ir = irs[-1]
            if record:
                out_T[k + 1 : e + 1] = Ts
                out_ir[k + 1 : e + 1] = irs
            if on_step is not None:
                for q in range(len(Ts)):
                    on_step(k + 1 + q, Ts[q], irs[q])
            k = e
        return out_T, (out_ir if record else ir)
