"""The iterative scattered-sunlight solve (fixed point, the compressed operator's path) against a direct
dense solve of the radiosity system ``(I - A F) B = A E`` on a real crater-like terrain (issue 24)."""

import numpy as np
import pytest

from crater_thermal import illumination, radiosity
from crater_thermal import vfoperator as vo
from crater_thermal.constants import AU
from crater_thermal.raytrace import RayTracer
from crater_thermal.reference import grid_mesh
from crater_thermal.viewfactors import view_factor_matrix

ALBEDO = 0.12


def _crater(n_facets=1200, size_m=20_000.0, diameter_m=10_000.0, depth_m=2_000.0):
    """A paraboloid crater in a plain on a regular grid (two triangles per cell)."""
    k = max(2, int(round(np.sqrt(n_facets / 2.0))))
    x = np.linspace(-size_m / 2, size_m / 2, k + 1)
    X, Y = np.meshgrid(x, x, indexing="xy")
    r = np.hypot(X, Y)
    z = np.where(r < diameter_m / 2, -depth_m * (1 - (2 * r / diameter_m) ** 2), 0.0)
    return grid_mesh(x, x, z)


@pytest.fixture(scope="module")
def terrain():
    m = _crater()
    tr = RayTracer(m)
    F = view_factor_matrix(m, tr)
    # a low Sun turning in azimuth, elevation -2..+6 deg: full night, a few lit facets, a lit wall
    az = np.radians(np.arange(0.0, 360.0, 15.0))
    el = np.radians(2.0 + 4.0 * np.sin(az))
    sun = np.column_stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    E = illumination.direct_irradiance(m, tr, sun, np.full(len(az), AU), disk=None)
    # and a sample with only a few lit facets (a sunlit peak above a dark landscape)
    few = np.zeros(m.n_facets)
    lit = np.flatnonzero(E[np.argmax(E.sum(axis=1))] > 0)[::40]
    few[lit] = 900.0
    return m, F, np.vstack([E, few])


def _dense_reference(F, E):
    """Q = E + F B with B from a dense LU solve of (I - A F) B = A E, all samples at once [W m-2]."""
    Fd = F.toarray()
    M = np.eye(Fd.shape[0]) - ALBEDO * Fd
    B = np.linalg.solve(M, ALBEDO * E.T)
    return E + (Fd @ B).T


def _bound(F, E):
    """Largest error the iterative solve's stopping rule allows [W m-2]: the last change is at most
    ITERATIVE_RTOL times the largest exitance A max(E); the iterate before it (whose product F B' is the
    returned scattered light) is then within change / (1 - q) of the fixed point, q = A max(rowsum) the
    contraction factor, and F (row sums <= 1) carries that error at most once more."""
    q = ALBEDO * float(np.asarray(F.sum(axis=1)).max())
    return radiosity.ITERATIVE_RTOL * ALBEDO * float(E.max()) / (1.0 - q)


def test_iterative_scattering_matches_dense_solve(terrain):
    m, F, E = terrain
    dark = ~np.any(E > 0, axis=1)
    few = (E > 0).sum(axis=1) < 0.05 * m.n_facets
    assert dark.any() and (few & ~dark).any() and (~few).any()  # the three regimes are covered
    ref = _dense_reference(F, E)
    for op in (vo.SparseViewFactors(F), vo.compressed_view_factors(m, leaf_size=16)):
        solver = radiosity.ScatteringSolver(op, ALBEDO, solver="iterative")
        Q = solver.solar_incident(E)
        # samples without sunlight anywhere are skipped: exactly the direct light (zero)
        assert np.array_equal(Q[dark], E[dark])
        err = np.abs(Q - ref).max()
        if op.kind == "exact":
            assert err <= _bound(F, E)
        else:
            # the compressed operator adds its own product error (issue 13: <= 1e-3 relative of F x);
            # the scattered light is <= A of the exitance's scale: 1e-3 of the largest scattered irradiance
            assert err <= 1e-3 * np.abs(ref - E).max() + _bound(F, E)


def test_warm_start_gives_the_same_solution_in_fewer_products(terrain):
    """Started from the previous sample's multiply-scattered part the fixed point ends at the same
    solution (within the stopping rule) and, when the Sun has moved little, in no more products."""
    m, F, E = terrain
    solver = radiosity.ScatteringSolver(vo.SparseViewFactors(F), ALBEDO, solver="iterative")
    ref = _dense_reference(F, E)
    Fd = F.toarray()
    prev, cold, warm = None, 0, 0
    for k in np.flatnonzero(np.any(E > 0, axis=1)):
        rhs = ALBEDO * E[k]
        solver.exitance(E[k])
        cold += solver.iterations
        B = solver.exitance(E[k], None if prev is None else rhs + prev)
        warm += solver.iterations
        assert np.abs(E[k] + Fd @ B - ref[k]).max() <= 2 * _bound(F, E)  # B itself, one product more
        prev = B - rhs
    assert warm <= cold


def test_blocks_per_facet_albedo_and_warm_start_match_dense_solve(terrain, monkeypatch):
    """Several blocks of samples (block of 5), a per-facet albedo with facets that reflect nothing (A = 0)
    and a warm start from the dense solution's neighbour: exitance and incident light against a dense LU
    solve of (I - diag(A) F) B = diag(A) E, within the stopping rule's bound; a sample lit only on
    non-reflecting facets scatters nothing."""
    m, F, E = terrain
    monkeypatch.setattr(radiosity, "ITERATIVE_BLOCK", 5)
    rng = np.random.default_rng(7)
    A = rng.uniform(0.05, 0.3, m.n_facets)
    A[rng.random(m.n_facets) < 0.2] = 0.0
    only_dark_reflectors = np.zeros(m.n_facets)
    only_dark_reflectors[np.flatnonzero(A == 0.0)[:10]] = 800.0
    E = np.vstack([E, only_dark_reflectors])
    Fd = F.toarray()
    B_ref = np.linalg.solve(np.eye(m.n_facets) - A[:, None] * Fd, (A * E).T).T
    Q_ref = E + B_ref @ Fd.T
    bound = radiosity.ITERATIVE_RTOL * float((A * E).max()) / (1.0 - float((A[:, None] * Fd).sum(axis=1).max()))
    solver = radiosity.ScatteringSolver(vo.SparseViewFactors(F), A, solver="iterative")
    assert np.abs(solver.exitance(E) - B_ref).max() <= 2 * bound
    assert np.abs(solver.solar_incident(E) - Q_ref).max() <= 2 * bound
    assert np.abs(solver.exitance(E, B0=np.roll(B_ref, 1, axis=0)) - B_ref).max() <= 2 * bound
    assert np.array_equal(solver.solar_incident(E[-1]), E[-1])
    assert np.abs(solver.exitance(E[3]) - B_ref[3]).max() <= 2 * bound  # one sample, (nf,)


class _Deferred(vo.SparseViewFactors):
    """The exact matrix as an asynchronous operator (as a cluster's is): a product is made only when its
    ``result()`` is asked for; the products in flight are counted."""

    asynchronous = True

    def __init__(self, F):
        super().__init__(F)
        self.in_flight = self.most_in_flight = 0

    def submit(self, x):
        x = np.array(x, dtype=float)  # the operand as it was sent: the solve may update its array next
        self.in_flight += 1
        self.most_in_flight = max(self.most_in_flight, self.in_flight)
        op = self

        class Pending:
            def result(self):
                op.in_flight -= 1
                return op.matvec(x)

        return Pending()


def test_solves_in_flight_with_an_asynchronous_operator(terrain, monkeypatch):
    """With an operator whose products run elsewhere, :data:`radiosity.ASYNC_SOLVES` blocks' fixed points
    run interleaved (the others' products in flight while one is updated, never more): the same exitance
    and incident light as one block at a time, bit for bit (the same operations per block), and against a
    dense solve within the stopping rule's bound."""
    m, F, E = terrain
    monkeypatch.setattr(radiosity, "ITERATIVE_BLOCK", 5)  # 5 blocks of lit samples
    ref = _dense_reference(F, E)
    one = radiosity.ScatteringSolver(vo.SparseViewFactors(F), ALBEDO, solver="iterative")
    op = _Deferred(F)
    two = radiosity.ScatteringSolver(op, ALBEDO, solver="iterative")
    Q = two.solar_incident(E)
    assert radiosity.ASYNC_SOLVES < 5  # more blocks than solves in flight: a block waits for a slot
    assert op.most_in_flight == radiosity.ASYNC_SOLVES and op.in_flight == 0
    assert np.array_equal(Q, one.solar_incident(E))
    assert np.array_equal(two.exitance(E), one.exitance(E))
    assert two.iterations == one.iterations
    assert np.abs(Q - ref).max() <= _bound(F, E)
