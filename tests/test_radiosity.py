"""Scattered sunlight, infrared exchange and radiative equilibrium on hand-made view factors."""

import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

from crater_thermal import radiosity as rs
from crater_thermal.constants import SIGMA
from crater_thermal.errors import ConfigError


def _reciprocal_F(nf=40, seed=1, max_rowsum=0.8, density=0.5):
    """Random view factors with reciprocity a_i F_ij = a_j F_ji and row sums <= max_rowsum."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.5, 2.0, nf)  # facet areas [m2]
    G = rng.uniform(0, 1, (nf, nf)) * (rng.uniform(0, 1, (nf, nf)) < density)
    G = np.triu(G, 1)
    G = G + G.T  # symmetric "exchange" a_i F_ij
    F = G / a[:, None]
    F *= max_rowsum / F.sum(axis=1).max()
    return sp.csr_matrix(F), a


def _ideal_bowl(nf=60, gamma=0.2, seed=2):
    """Ingersoll's bowl in the abstract: every element sees every element (itself included,
    as for infinitesimal elements) with F_ij = f a_j / a_total."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.5, 2.0, nf)
    f = rs.bowl_view_factor(gamma)
    F = np.tile(f * a / a.sum(), (nf, 1))
    return F, a, f


@pytest.mark.parametrize("method", ["exact", "bounces"])
def test_no_albedo_means_no_scattering(method):
    F, a = _reciprocal_F()
    E = np.random.default_rng(3).uniform(0, 500, (5, F.shape[0]))
    Q = rs.ScatteringSolver(F, 0.0, method).solar_incident(E)
    np.testing.assert_array_equal(Q, E)
    # total absorbed (1 - A = 1) equals total direct
    assert np.sum(Q * a) == pytest.approx(np.sum(E * a), rel=1e-14)


def test_exact_radiosity_global_energy_balance():
    """Power in = power absorbed + power escaping to the sky.

    in: sum a_i E_i; absorbed: sum a_i (1 - A_i) Q_i; escaping: exitance B_i times the part of
    the hemisphere not covered by facets, sum a_i B_i (1 - sum_j F_ij). Holds exactly for the
    exact solution when F is reciprocal (tolerance: LU round-off, 1e-12 relative).
    """
    F, a = _reciprocal_F(max_rowsum=0.9)
    nf = F.shape[0]
    rng = np.random.default_rng(4)
    A = rng.uniform(0.05, 0.6, nf)
    E = rng.uniform(0, 800, (3, nf))
    solver = rs.ScatteringSolver(F, A, "exact")
    Q = solver.solar_incident(E)
    B = solver.exitance(E)
    np.testing.assert_allclose(B, A * Q, rtol=1e-12)  # Lambertian: exitance = albedo * incident
    escape = 1.0 - np.asarray(F.sum(axis=1)).ravel()
    p_in = E @ a
    p_abs = ((1 - A) * Q) @ a
    p_esc = (B * escape) @ a
    np.testing.assert_allclose(p_abs + p_esc, p_in, rtol=1e-12)


def test_bounces_converge_to_exact():
    F, a = _reciprocal_F(max_rowsum=0.95)
    A = 0.5
    E = np.random.default_rng(5).uniform(0, 1000, F.shape[0])
    exact = rs.ScatteringSolver(F, A, "exact").solar_incident(E)
    scattered = exact - E
    errs = []
    for n in range(0, 9):
        Q = rs.ScatteringSolver(F, A, "bounces", n_bounces=n).solar_incident(E)
        errs.append(np.abs(Q - exact).max())
    assert np.all(np.diff(errs) < 0)
    # the Neumann tail after n reflections is bounded by (A * max row sum)^n times the scattered light
    q = A * 0.95
    for n, e in enumerate(errs):
        assert e <= q**n * np.abs(scattered).max() / (1 - q) + 1e-9
    # thesis: 3 bounces with A = 0.12 lose < 0.2% of the scattered light (0.12^3 = 0.0017)
    Q3 = rs.ScatteringSolver(F, 0.12, "bounces", 3).solar_incident(E)
    Qx = rs.ScatteringSolver(F, 0.12, "exact").solar_incident(E)
    assert np.abs(Q3 - Qx).max() <= 0.12**3 / (1 - 0.12) * np.abs(Qx - E).max()


def test_one_bounce_is_F_A_E():
    F, _ = _reciprocal_F()
    E = np.random.default_rng(6).uniform(0, 100, F.shape[0])
    Q = rs.ScatteringSolver(F, 0.3, "bounces", 1).solar_incident(E)
    np.testing.assert_allclose(Q, E + F @ (0.3 * E), rtol=1e-13)


def test_ir_incident_closed_enclosure():
    """Inside a closed isothermal sphere (F_ij = a_j / a_total, row sums 1) every facet
    receives eps sigma T^4; with one facet hotter, each gets its share F_ij of it."""
    rng = np.random.default_rng(10)
    a = rng.uniform(0.5, 2.0, 30)
    F = sp.csr_matrix(np.tile(a / a.sum(), (30, 1)))
    T = np.full((2, 30), 120.0)
    q = rs.ir_incident(F, T, 0.95)
    assert q.shape == T.shape
    np.testing.assert_allclose(q, 0.95 * SIGMA * 120.0**4, rtol=1e-13)
    T[1, 7] = 300.0
    q = rs.ir_incident(F.toarray(), T[1], 0.95)  # dense input too
    expect = 0.95 * SIGMA * (120.0**4 + (a[7] / a.sum()) * (300.0**4 - 120.0**4))
    np.testing.assert_allclose(q, expect, rtol=1e-13)


def test_equilibrium_without_neighbours_is_local_balance():
    F = sp.csr_matrix((5, 5))
    Q = np.array([0.0, 10.0, 100.0, 1000.0, 1361.0])
    T = rs.equilibrium_temperature(F, Q, 0.12, 0.98)
    np.testing.assert_allclose(0.98 * SIGMA * T**4, 0.88 * Q, rtol=1e-12)


def test_equilibrium_balances_every_facet():
    F, a = _reciprocal_F(max_rowsum=0.9)
    E = np.random.default_rng(7).uniform(0, 900, F.shape[0])
    Q = rs.ScatteringSolver(F, 0.12).solar_incident(E)
    T = rs.equilibrium_temperature(F, Q, 0.12, 0.95)
    # surface balance with no conduction: (1-A) Q + eps Q_ir = eps sigma T^4 on every facet
    lhs = 0.88 * Q + 0.95 * rs.ir_incident(F, T, 0.95)
    np.testing.assert_allclose(lhs, 0.95 * SIGMA * T**4, rtol=1e-11)


def test_ideal_bowl_matches_analytic_exactly():
    """With Ingersoll's ideal view factors the solver reproduces the analytic shadow temperature
    of this model (no IR reflection) to round-off, for any distribution of the direct light."""
    F, a, f = _ideal_bowl()
    rng = np.random.default_rng(8)
    lit = rng.uniform(0, 1, F.shape[0]) < 0.5
    E = np.where(lit, rng.uniform(100, 1300, F.shape[0]), 0.0)
    Ed = E @ a / a.sum()  # bowl-mean direct flux
    A, eps = 0.12, 0.95
    Q = rs.ScatteringSolver(F, A).solar_incident(E)
    T = rs.equilibrium_temperature(F, Q, A, eps)
    u = (1 - A) * f * Ed / (1 - A * f) * (A + eps / (1 - eps * f))
    np.testing.assert_allclose(eps * SIGMA * T[~lit] ** 4, u, rtol=1e-12)


def test_dense_and_sparse_factorisations_agree(monkeypatch):
    F, _ = _reciprocal_F(density=0.05, nf=60)
    E = np.random.default_rng(9).uniform(0, 500, (4, 60))
    monkeypatch.setattr(rs, "DENSE_FILL", 2.0)  # force SuperLU
    q_sparse = rs.ScatteringSolver(F, 0.3).solar_incident(E)
    monkeypatch.setattr(rs, "DENSE_FILL", 0.0)  # force LAPACK
    q_dense = rs.ScatteringSolver(F, 0.3).solar_incident(E)
    np.testing.assert_allclose(q_sparse, q_dense, rtol=1e-12)


@pytest.mark.parametrize(
    "call",
    [
        lambda F: rs.ScatteringSolver(F, 1.0),
        lambda F: rs.ScatteringSolver(F, -0.1),
        lambda F: rs.ScatteringSolver(F, 0.1, method="magic"),
        lambda F: rs.ScatteringSolver(F, 0.1, "bounces", n_bounces=-1),
        lambda F: rs.ScatteringSolver(F, 0.1).solar_incident(np.zeros(3)),
        lambda F: rs.ir_incident(F, np.zeros(3), 0.9),
        lambda F: rs.ir_incident(F, np.zeros(F.shape[0]), 1.5),
        lambda F: rs.equilibrium_temperature(F, np.zeros(F.shape[0]), 0.1, 0.0),
        lambda F: rs.ScatteringSolver(np.zeros((3, 4)), 0.1),
    ],
)
def test_bad_input(call):
    F, _ = _reciprocal_F(nf=8)
    with pytest.raises(ConfigError):
        call(F)


# ----------------------------------------------------------------------------- steady + CLI


def _bowl_file(tmp_path, n=200):
    geometry = pytest.importorskip("crater_thermal.geometry")
    path = tmp_path / "bowl.ply"
    geometry.save_mesh(geometry.bowl_mesh(0.2, n), path)
    return path


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "crater_thermal", *map(str, args)], capture_output=True, text=True)


def test_steady_cli_writes_and_refuses_to_overwrite(tmp_path):
    pytest.importorskip("crater_thermal.io")
    import xarray as xr

    mesh = _bowl_file(tmp_path)
    out = tmp_path / "steady.nc"
    r = _cli("steady", mesh, "--sun-elevation-deg", 10, "--emissivity", 0.95, "--point-sun", "-o", out)
    assert r.returncode == 0, r.stderr
    with xr.open_dataset(out) as ds:
        for name in ("surface_temperature", "solar_direct", "solar_incident", "ir_incident"):
            assert ds[name].dims == ("facet",)
        assert ds.attrs["albedo"] == pytest.approx(0.12)
        assert ds.attrs["emissivity"] == pytest.approx(0.95)
        T = ds["surface_temperature"].values
        Ed = ds["solar_direct"].values
        # sunlit facets at radiative equilibrium are warmer than the shadowed ones
        assert T[Ed > 0].mean() > T[Ed == 0].mean() > 100.0
    r = _cli("steady", mesh, "--sun-elevation-deg", 10, "-o", out)
    assert r.returncode == 2 and "exists" in r.stderr and "Traceback" not in r.stderr
    r = _cli("steady", mesh, "--sun-elevation-deg", 10, "--sun-azimuth-deg", 90, "-o", out, "--overwrite")
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize(
    "args, word",
    [
        (["--sun-elevation-deg", "95"], "sun_elevation_deg"),
        (["--sun-elevation-deg", "-90.5"], "sun_elevation_deg"),
        (["--sun-elevation-deg", "10", "--albedo", "1.0"], "albedo"),
        (["--sun-elevation-deg", "10", "--albedo", "-0.1"], "albedo"),
        (["--sun-elevation-deg", "10", "--emissivity", "0"], "emissivity"),
        (["--sun-elevation-deg", "10", "--limb-darkening", "sepia"], "limb_darkening"),
    ],
)
def test_steady_cli_bad_input(tmp_path, args, word):
    mesh = tmp_path / "m.ply"
    mesh.write_text("not read: arguments are checked first")
    r = _cli("steady", mesh, *args, "-o", tmp_path / "o.nc")
    assert r.returncode == 2
    assert word in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert not (tmp_path / "o.nc").exists()


def test_steady_cli_missing_mesh(tmp_path):
    r = _cli("steady", tmp_path / "nope.ply", "--sun-elevation-deg", "10", "-o", tmp_path / "o.nc")
    assert r.returncode == 2 and "nope.ply" in r.stderr and "Traceback" not in r.stderr
