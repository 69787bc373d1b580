"""Profiles, grid and the nonlinear column solver (crater_thermal.thermal + kernels.conduction)."""

import warnings

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from crater_thermal import materials as mat
from crater_thermal import reference
from crater_thermal import thermal as th
from crater_thermal.constants import LUNAR_DAY, SIGMA, YEAR
from crater_thermal.errors import ConfigError, ProfileError, SolverError
from crater_thermal.kernels import conduction as _kern

_LANES = _kern.LANES

FLUX_STEP = 14_400.0  # thesis flux step [s]


#: Synthetic absorbed flux [W m-2] of a shadowed floor and a sunlit wall (shared with bench/conduction_accuracy.py)
forcing = reference.synthetic_absorbed_flux


def quiet_solver(*args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mat.DensityExtrapolationWarning)
        return th.ColumnSolver(*args, **kw)


# ----------------------------------------------------------------------------- profiles


def test_parse_two_layer_profile():
    p = th.parse_profile("1300/1800")
    assert p.label == "1300/1800" and p.material == "regolith"
    assert p.layers == ((0.02, 1300.0), (2.0, 1800.0))
    assert p.rho_top == 1300.0 and p.rho_bottom == 1800.0
    assert p.interfaces == (0.02,)
    # areal mass of the top 10 cm: 2 cm of 1300 + 8 cm of 1800 kg/m3
    assert float(p.mass_between(0.0, 0.1)) == pytest.approx(0.02 * 1300 + 0.08 * 1800, rel=1e-12)


def test_parse_rock_hayne_and_layer_list():
    rock = th.parse_profile("rock")
    assert rock.material == "rock" and rock.rho_top == 3070.0
    h = th.parse_profile("hayne2017")
    assert h.rho_top == 1100.0 and h.rho_bottom == pytest.approx(1800.0, abs=1e-6)
    # exponential profile: mean density of the top H = 6 cm is rho_d - (rho_d - rho_s)(1 - 1/e)
    assert float(h.mean_density(0.0, 0.06)) == pytest.approx(1800 - 700 * (1 - np.exp(-1)), rel=1e-12)
    p = th.parse_profile([(0.05, 1400), (0.5, 1600), (2.0, 1800)])
    assert p.interfaces == (0.05, 0.5) and p.label == "0.05:1400,0.5:1600,2:1800"


def test_profile_errors_and_warnings():
    with pytest.raises(ProfileError, match="decreases with depth"):
        th.parse_profile("1800/1300")
    assert th.parse_profile("1800/1300", allow_inverted=True).rho_top == 1800.0
    with pytest.raises(ProfileError, match="500-3500"):
        th.parse_profile("400/1800")
    with pytest.raises(ProfileError, match="500-3500"):
        th.parse_profile("1300/3600")
    with pytest.raises(ProfileError, match="not understood"):
        th.parse_profile("1300-1800")
    with pytest.raises(ProfileError, match="increasing"):
        th.parse_profile([(0.5, 1400), (0.1, 1600)])
    with pytest.warns(mat.DensityExtrapolationWarning, match="800"):
        th.parse_profile("800/1100")


def test_density_grid_profiles():
    with pytest.warns(mat.DensityExtrapolationWarning):
        profs = th.density_grid_profiles("800:2000:100")
    assert len(profs) == 91  # 13 densities, top <= bottom: 13 * 14 / 2
    assert all(p.rho_top <= p.rho_bottom for p in profs)
    assert profs[0].label == "800/800" and profs[-1].label == "2000/2000"
    assert len({p.label for p in profs}) == 91
    for bad in ("800:2000", "a:b:c", "2000:800:100", "800:2000:0", "400:2000:100", "800:2000:-5"):
        with pytest.raises(ProfileError, match="density_grid"):
            th.density_grid_profiles(bad)


# ----------------------------------------------------------------------------- grid


def test_default_grid():
    g = th.make_grid()
    delta = th.skin_depth()
    assert 0.03 < delta < 0.045  # 1300 kg/m3 at 250 K, lunar day: ~3.6 cm
    assert g.first_layer_m == pytest.approx(th.DEFAULT_SKIN_FRACTION * delta)
    assert g.z[0] == 0.0 and g.z[-1] == 2.0
    assert 0.02 in g.z  # exact node on the layer interface
    ratios = g.dz[1:] / g.dz[:-1]
    # geometric growth, shrunk slightly inside each segment to land on the interface
    assert np.all(np.abs(ratios[np.abs(g.z[1:-1] - 0.02) > 1e-12] - th.DEFAULT_GROWTH) < 1e-9)
    assert g.dz[0] <= g.first_layer_m + 1e-15
    assert 20 <= g.nz <= 40
    with pytest.raises(ConfigError, match="growth"):
        th.make_grid(growth=0.5)


# ----------------------------------------------------------------------------- analytic checks


def test_periodic_flux_damped_wave():
    """Constant properties, no emission, surface flux F1 cos(wt): the surface temperature of a
    half-space is T0 + F1 / (I sqrt(w)) cos(wt - pi/4) (I = sqrt(k rho c)). The 2 m column is
    ~65 skin depths deep, so it is a half-space. Default grid and dt (4 h: 177 steps a period)."""
    k, rho, c = 1e-3, 1500.0, 600.0
    cs = mat.constant_set(k, rho, c)
    P = LUNAR_DAY
    w = 2 * np.pi / P
    I = np.sqrt(k * rho * c)
    F1 = 0.03
    A = F1 / (I * np.sqrt(w))  # ~20 K
    s = th.ColumnSolver(["1300/1800"], property_set=cs, emissivity=0.0, geothermal_flux=0.0)
    d = np.sqrt(2 * k / (rho * c * w))
    z = s.grid.z
    T0 = 200.0
    s.set_state((T0 + A * np.exp(-z / d) * np.cos(-z / d - np.pi / 4))[None, :])
    t = np.arange(0.0, 3 * P, FLUX_STEP)
    T = s.run_series(t, F1 * np.cos(w * t))[:, 0]
    last = t >= P
    X = np.column_stack([np.ones(last.sum()), np.cos(w * t[last]), np.sin(w * t[last])])
    coef, *_ = np.linalg.lstsq(X, T[last], rcond=None)
    amp = np.hypot(coef[1], coef[2])
    lag = np.arctan2(coef[2], coef[1])
    assert amp == pytest.approx(A, rel=0.01)
    assert lag == pytest.approx(np.pi / 4, rel=0.01)
    assert coef[0] == pytest.approx(T0, abs=0.01 * A)


@pytest.mark.parametrize("which", ["constant", "1300/1800", "rock"])
def test_geothermal_steady_state(which):
    """Constant absorbed flux Q: steady state has eps sigma Ts^4 = Q + G and dT/dz = G / k(T, z).
    Backward steps of 1e9 s (the scheme is L-stable) reach the fixed point."""
    Q, G, eps = 2.0, 0.033, 0.98
    if which == "constant":
        s = th.ColumnSolver(
            ["1300/1800"],
            property_set=mat.constant_set(2e-3, 1500.0, 500.0),
            emissivity=eps,
            geothermal_flux=G,
            dt_max=1e9,
        )
    else:
        s = th.ColumnSolver([which], emissivity=eps, geothermal_flux=G, dt_max=1e9)
    s.set_uniform(100.0)
    t = np.arange(0.0, 400.0) * 1e9
    s.run_series(t, np.full(t.size, Q), record=False)
    Ts = ((Q + G) / (eps * SIGMA)) ** 0.25
    z = s.grid.z
    if which == "constant":
        expect = Ts + G * z / 2e-3
    else:
        p = s.profiles[0]

        def rhs(zz, T):
            rho = float(p.mean_density(zz - 1e-9, zz + 1e-9))
            b0, b3, e0, e1 = mat.conductivity_coefficients(rho, p.material)
            k = b0 + b3 * T**3 + mat.heat_capacity(T) * (e0 + e1 / T)
            return G / k

        sol = solve_ivp(rhs, (0, 2.0), [Ts], t_eval=z, rtol=1e-10, atol=1e-10, max_step=0.005)
        expect = sol.y[0]
    # 0.01 K: the brief's tolerance for the steady geothermal profile (tens of K across 2 m)
    np.testing.assert_allclose(s.T[0], expect, atol=0.01)


def test_very_low_conductivity_tracks_radiative_equilibrium():
    """k -> 0 and tiny heat capacity: the surface is in instantaneous radiative equilibrium."""
    s = th.ColumnSolver(
        ["1300/1800"], property_set=mat.constant_set(1e-9, 100.0, 1.0), emissivity=0.95, geothermal_flux=0.0
    )
    t = np.arange(0.0, LUNAR_DAY, FLUX_STEP)
    Q = forcing("wall", t)
    s.set_uniform(float((Q[0] / (0.95 * SIGMA)) ** 0.25))
    T = s.run_series(t, Q)[:, 0]
    Teq = (Q / (0.95 * SIGMA)) ** 0.25
    # surface heat capacity ~0.1 J/m2/K: response time < 1 s, so equilibrium to 1e-3 relative
    np.testing.assert_allclose(T, Teq, rtol=1e-3)


# ----------------------------------------------------------------------------- energy, convergence


@pytest.mark.parametrize("scheme", ["trbdf2", "euler"])
def test_energy_balance(scheme):
    """absorbed - emitted + geothermal = change of stored heat (enthalpy), over one year, for
    regolith and rock under wall-like and floor-like forcing."""
    t = np.arange(0.0, YEAR, FLUX_STEP)
    Q = np.column_stack([forcing("wall", t), forcing("floor", t)] * 3)
    s = quiet_solver(["1300/1800"] * 2 + ["800/1100"] * 2 + ["rock"] * 2, scheme=scheme)
    s.set_equilibrium(Q)
    H0 = s.stored_heat()
    s.reset_accumulators()
    s.run_series(t, Q, record=False)
    b = s.energy_budget()
    dH = s.stored_heat() - H0
    budget = b["absorbed"] - b["emitted"] + b["geothermal"]
    # the scheme conserves energy exactly for its lagged capacities; against the exact enthalpy the
    # defect is O(c' dT^2) per step. 0.1% of the absorbed energy is the brief's tolerance for the
    # default TR-BDF2 (measured <= 5.3e-4, on sunlit rock); the first-order backward-Euler option
    # (capacities lagged over the whole 4 h step) reaches 1.1e-3 on sunlit rock, hence 2e-3 for it.
    rtol = 1e-3 if scheme == "trbdf2" else 2e-3
    np.testing.assert_array_less(np.abs(dH - budget), rtol * b["absorbed"])
    if scheme == "trbdf2":
        # TR-BDF2's quadrature of the absorbed flux is exact for piecewise-linear forcing
        quad = np.sum(0.5 * (Q[1:] + Q[:-1]) * np.diff(t)[:, None], axis=0)
    else:  # backward Euler (one sub-step per 4 h interval): right-end-point rule
        quad = np.sum(Q[1:] * np.diff(t)[:, None], axis=0)
    np.testing.assert_allclose(b["absorbed"], quad, rtol=1e-12)


def _night_run(first_layer_m, dt, kinds, profs, growth=th.DEFAULT_GROWTH):
    t = np.arange(0.0, 0.5 * YEAR, FLUX_STEP)
    Q = np.column_stack([forcing(k, t) for k in kinds])
    g = th.make_grid(first_layer_m=first_layer_m, growth=growth)
    s = quiet_solver(profs, grid=g, dt_max=dt)
    s.set_equilibrium(Q)
    return t, s.run_series(t, Q)


@pytest.mark.slow
def test_convergence_study():
    """Halving dt (4 h -> 2 h) and the first layer changes night-time surface temperatures by
    < 0.05 K, for nominal, loose and rock columns. Night: the Sun (for the floor: the walls'
    illumination, i.e. its IR) has been down for >= 1 day. In the first hours after sunset the
    surface cools by tens of K per 4 h step and the changes reach ~0.1-0.2 K on sunlit walls.
    This fixes DEFAULT_DT_MAX (= the 4 h flux step), DEFAULT_SKIN_FRACTION and DEFAULT_GROWTH."""
    kinds = ["floor", "wall"] * 3
    profs = ["1300/1800"] * 2 + ["800/1100"] * 2 + ["rock"] * 2
    f0 = th.make_grid().first_layer_m
    t, Ta = _night_run(f0, th.DEFAULT_DT_MAX, kinds, profs)
    _, Tb = _night_run(f0 / 2, th.DEFAULT_DT_MAX / 2, kinds, profs)
    _, Tc = _night_run(f0, th.DEFAULT_DT_MAX, kinds, profs, growth=1.1)
    ph = (t % LUNAR_DAY) / LUNAR_DAY  # sunset at 0.25, sunrise at 0.75
    settled_night = (ph > 0.25 + 1 / 29.5) & (ph < 0.75)
    late = t > 0.25 * YEAR
    for j, kind in enumerate(kinds):
        m = late & settled_night
        assert np.max(np.abs(Ta[m, j] - Tb[m, j])) < 0.05, (kind, profs[j])
        # and a finer geometric growth (1.1 instead of 1.2: 45 instead of 29 nodes)
        assert np.max(np.abs(Ta[m, j] - Tc[m, j])) < 0.05, (kind, profs[j], "growth")


# ----------------------------------------------------------------------------- API behaviour


def test_state_roundtrip_and_predictor_corrector_rewind():
    t = np.arange(0.0, 10 * FLUX_STEP, FLUX_STEP)
    Q = forcing("wall", t)[:, None] * np.ones(3)
    s = th.ColumnSolver(["1300/1800", "rock", "hayne2017"])
    s.set_equilibrium(Q)
    ref = th.ColumnSolver(["1300/1800", "rock", "hayne2017"])
    ref.set_state(s.state())
    Tref = ref.run_series(t, Q)
    for k in range(len(t) - 1):
        snap = s.state()
        s.advance(Q[k], Q[k + 1] + 50.0, FLUX_STEP)  # predictor with a wrong end flux
        s.set_state(snap)
        out = s.advance(Q[k], Q[k + 1], FLUX_STEP)
        np.testing.assert_array_equal(out, Tref[k + 1])
    assert s.time_s == pytest.approx(t[-1])
    np.testing.assert_allclose(s.acc, ref.acc, rtol=1e-14)  # the predictor left no trace
    np.testing.assert_array_equal(s.surface_temperature, s.T[:, 0])


def test_forcing_shared_by_profiles():
    """absorbed with n < ncol columns: column j uses forcing column j % n (profile-major tiling)."""
    t = np.arange(0.0, 20 * FLUX_STEP, FLUX_STEP)
    Q = np.column_stack([forcing("wall", t), forcing("floor", t)])
    a = th.ColumnSolver(["1300/1800"] * 2 + ["rock"] * 2)
    b = th.ColumnSolver(["1300/1800"] * 2 + ["rock"] * 2)
    a.set_uniform(150.0)
    b.set_uniform(150.0)
    np.testing.assert_array_equal(a.run_series(t, Q), b.run_series(t, np.tile(Q, (1, 2))))


def test_float32_output_buffer():
    t = np.arange(0.0, 20 * FLUX_STEP, FLUX_STEP)
    Q = forcing("wall", t)[:, None]
    a = th.ColumnSolver(["1300/1800"] * 3)
    b = th.ColumnSolver(["1300/1800"] * 3)
    a.set_uniform(150.0)
    b.set_uniform(150.0)
    buf = np.empty((t.size, 3), np.float32)
    assert a.run_series(t, Q, out=buf) is buf
    np.testing.assert_array_equal(buf, b.run_series(t, Q).astype(np.float32))
    with pytest.raises(SolverError, match="out must be"):
        a.run_series(t, Q, out=np.empty((t.size, 2)))


def test_nan_forcing_names_column_and_time():
    s = th.ColumnSolver(["1300/1800"] * 20)
    s.set_uniform(100.0)
    t = np.arange(0.0, 5 * FLUX_STEP, FLUX_STEP)
    Q = np.full((t.size, 20), 3.0)
    Q[3, 17] = np.nan
    with pytest.raises(SolverError, match=r"column 17 .*t=28800 s"):
        s.run_series(t, Q)
    s = th.ColumnSolver(["1300/1800"] * 20, column_labels=[f"facet {i}" for i in range(20)])
    s.set_uniform(100.0)
    with pytest.raises(SolverError, match="column 2 .*facet 2"):
        s.advance(np.array([1.0] * 20), np.array([1.0, 1.0, np.inf] + [1.0] * 17), FLUX_STEP)


def test_bad_solver_inputs():
    s = th.ColumnSolver(["1300/1800"] * 3)
    with pytest.raises(SolverError, match="shape"):
        s.set_state(np.full((2, s.nz), 100.0))
    with pytest.raises(SolverError, match="T0"):
        s.set_uniform(-5.0)
    with pytest.raises(SolverError, match="divisor"):
        s.run_series([0.0, 1.0], np.ones((2, 2)))
    with pytest.raises(SolverError, match="increasing"):
        s.run_series([0.0, 0.0], np.ones((2, 3)))
    with pytest.raises(ConfigError, match="scheme"):
        th.ColumnSolver(["1300/1800"], scheme="rk4")
    with pytest.raises(ProfileError, match="500-3500"):
        th.ColumnSolver([th.Profile("x", ((0.02, 1800.0), (2.0, 4000.0)))])


def test_default_start_is_equilibrium():
    t = np.arange(0.0, 5 * FLUX_STEP, FLUX_STEP)
    Q = np.column_stack([forcing("wall", t), forcing("floor", t)])
    a = th.ColumnSolver(["1300/1800"] * 2)
    b = th.ColumnSolver(["1300/1800"] * 2)
    b.set_equilibrium(Q)
    np.testing.assert_array_equal(a.run_series(t, Q), b.run_series(t, Q))
    # the equilibrium estimate: mean radiative-equilibrium surface, steady geothermal gradient below
    eq = b.equilibrium_profile(Q)
    Ts = np.mean(((Q + 0.033) / (0.98 * SIGMA)) ** 0.25, axis=0)
    np.testing.assert_allclose(eq[:, 0], Ts, rtol=1e-12)
    k = b.conductivity(eq)
    np.testing.assert_allclose(k * np.diff(eq, axis=1) / b.dz, 0.033, rtol=1e-3)


def test_adaptive_refinement_at_sunset():
    """The sub-step right after sunset (a kink in the forcing while the surface cools fast) is the
    least accurate one at 4 h; the adaptive refinement (DEFAULT_ADAPT_K) must shrink its error
    against a 15-minute reference (bench/conduction_accuracy.py: 0.6 -> 0.15-0.18 K over half a
    year). The refinement is decided per column: a column's result must not depend on the other
    columns advanced with it (replays in other chunks must reproduce the coupled run)."""
    t = np.arange(0.0, 3 * LUNAR_DAY, FLUX_STEP)
    Q = forcing("wall", t)[:, None]
    runs = {}
    for name, kw in {"ref": dict(dt_max=900.0, adapt_K=0.0), "off": dict(adapt_K=0.0), "on": {}}.items():
        s = th.ColumnSolver(["1300/1800"], **kw)
        s.set_equilibrium(Q)
        runs[name] = s.run_series(t, Q)[:, 0]
    ph = (t % LUNAR_DAY) / LUNAR_DAY
    first_day = (ph > 0.25) & (ph <= 0.25 + 1 / 29.5) & (t > LUNAR_DAY)
    err_on = np.max(np.abs(runs["on"] - runs["ref"])[first_day])
    err_off = np.max(np.abs(runs["off"] - runs["ref"])[first_day])
    assert err_on < 0.3 and err_on < 0.8 * err_off
    # batch independence: the same wall among 20 floor columns (one 16-lane batch and a partial one)
    s = th.ColumnSolver(["1300/1800"] * 21)
    Qm = np.tile(forcing("floor", t)[:, None], (1, 21))
    Qm[:, 9] = Q[:, 0]
    s.set_equilibrium(Q[:, [0] * 21])
    # (not bitwise: vectorised and scalar code round differently; a different refinement decision
    # would show as ~0.1 K)
    np.testing.assert_allclose(s.run_series(t, Qm)[:, 9], runs["on"], rtol=0, atol=1e-6)


@pytest.mark.parametrize("take", ["state", "snapshot"])
def test_redo_columns_is_the_step_with_the_other_forcing(take):
    """ColumnSolver.redo_columns (the coupled step's second try for some columns): the same state and
    energy accumulators as one step taken with the new forcing for those columns from the start, whether
    the start is a kept copy (state) or the reused buffer (snapshot)."""
    n = 7
    a0 = np.linspace(0.0, 300.0, n)
    a1, b1 = np.linspace(5.0, 250.0, n), np.linspace(20.0, 40.0, n)
    cols = np.array([1, 4, 6])
    ref_end = a1.copy()
    ref_end[cols] = b1[cols]
    s, ref = th.ColumnSolver(["1300/1800"] * n), th.ColumnSolver(["1300/1800"] * n)
    for x in (s, ref):
        x.set_uniform(150.0)
    start = getattr(s, take)()
    s.advance(a0, a1, 14400.0)
    T_cols = s.redo_columns(cols, start, a0[cols], b1[cols], 14400.0)
    ref.advance(a0, ref_end, 14400.0)
    np.testing.assert_array_equal(s.T, ref.T)
    np.testing.assert_array_equal(T_cols, ref.T[cols, 0])
    np.testing.assert_array_equal(s.acc, ref.acc)
    assert s.time_s == ref.time_s


def test_rerun_columns_is_the_series_with_the_other_forcing():
    """ColumnSolver.rerun_columns (a group of coupled steps taken again for some columns, issue 24): the same
    state, recorded surface temperatures and energy accumulators as the series run with the new forcing
    for those columns from the start; the other columns and the clock untouched."""
    n = 9
    t = 1.0e6 + np.array([0.0, 14400.0, 28800.0, 43200.0])
    rng = np.random.default_rng(5)
    a = rng.uniform(0.0, 300.0, (4, n))
    b = rng.uniform(0.0, 60.0, (4, n))
    cols = np.array([0, 3, 8])
    ref_a = a.copy()
    ref_a[:, cols] = b[:, cols]
    ref_a[0] = a[0]  # the start's forcing is the run's
    s, ref = th.ColumnSolver(["1300/1800"] * n), th.ColumnSolver(["1300/1800"] * n)
    for x in (s, ref):
        x.set_uniform(150.0)
    start = s.snapshot()
    s.run_series(t, a)
    sub = b[:, cols].copy()
    sub[0] = a[0, cols]
    T_cols = s.rerun_columns(cols, start, t, sub)
    T_ref = ref.run_series(t, ref_a)
    np.testing.assert_array_equal(T_cols, T_ref[:, cols])
    np.testing.assert_array_equal(s.T, ref.T)
    np.testing.assert_array_equal(s.acc, ref.acc)
    assert s.time_s == ref.time_s
    with pytest.raises(SolverError, match="rerun_columns"):
        s.rerun_columns(cols, start.copy(), t, sub)


def test_snapshot_reuses_one_buffer_and_rewinds_like_state():
    """snapshot(): the state's values in a buffer that the next snapshot overwrites (no new array per
    step); set_state of it rewinds the clock and energy accumulators as set_state(state()) does."""
    s = th.ColumnSolver(["1300/1800"] * 5)
    s.set_uniform(150.0)
    first = s.snapshot()
    T0, acc0, t0 = s.T.copy(), s.acc.copy(), s.time_s
    np.testing.assert_array_equal(first, T0)
    s.advance(np.full(5, 300.0), np.full(5, 280.0), 14400.0)
    assert not np.array_equal(s.T, T0)
    np.testing.assert_array_equal(first, T0)  # the step did not write into the snapshot
    second = s.snapshot()
    assert second is first  # the same buffer, now holding the new state
    np.testing.assert_array_equal(second, s.T)
    acc1 = s.acc.copy()
    s.advance(np.full(5, 280.0), np.full(5, 10.0), 14400.0)
    s.set_state(second)
    np.testing.assert_array_equal(s.T, second)
    assert s.T is not second  # the solver owns its state; the buffer stays the snapshot's
    assert s.time_s == t0 + 14400.0
    np.testing.assert_array_equal(s.acc, acc1)  # the first step's energies kept, the second's rewound
    assert not np.array_equal(acc1, acc0)


def test_redo_columns_failure_names_the_solver_column():
    """A failure while a subset of columns is taken again names the column of the solver, not its
    position in the subset."""
    s = th.ColumnSolver(["1300/1800"] * 7)
    s.set_uniform(150.0)
    start = s.state()
    s.advance(np.full(7, 10.0), np.full(7, 10.0), 14400.0)
    with pytest.raises(SolverError, match=r"column 4 .*t=0 s"):
        s.redo_columns(np.array([1, 4, 6]), start, np.full(3, 10.0), np.array([10.0, np.nan, 10.0]), 14400.0)
    # only from the snapshot the step was taken from (its energy accumulators are rewound with it)
    with pytest.raises(SolverError, match="latest state"):
        s.redo_columns(np.array([1]), start.copy(), np.full(1, 10.0), np.full(1, 10.0), 14400.0)


# 5 batches of LANES columns: enough for the kernel's threaded path (from 2 batches per thread), the last
# batch partly filled
@pytest.mark.parametrize(
    "labels",
    [["1300/1800"] * (4 * _LANES + 7), (["1300/1800", "rock", "1100/1900", "1300/1800"] * _LANES)[: 4 * _LANES + 7]],
)
def test_columns_alike_or_not_match_each_column_alone(labels):
    """Alike columns (one profile) share one batch of coefficients in the kernel; any mix keeps them per
    column. Either way every column equals the same column solved alone, bit for bit, through a series
    and through one-step calls (the kernel never lets a column's result depend on its batch)."""
    t = np.arange(0.0, 30 * FLUX_STEP, FLUX_STEP)
    kinds = ("wall", "floor")
    Q = np.column_stack([forcing(kinds[j % 2], t) * (0.5 + 0.03 * j) for j in range(len(labels))])
    many = th.ColumnSolver(labels)
    many.set_uniform(150.0)
    T_many = many.run_series(t, Q)
    for k in range(5):
        many.advance(Q[k], Q[k + 1], FLUX_STEP)
    for j in (0, 1, 2, 17, _LANES + 1, len(labels) - 1):
        one = th.ColumnSolver([labels[j]])
        one.set_uniform(150.0)
        np.testing.assert_array_equal(one.run_series(t, Q[:, j : j + 1])[:, 0], T_many[:, j])
        for k in range(5):
            one.advance(Q[k, j : j + 1], Q[k + 1, j : j + 1], FLUX_STEP)
        np.testing.assert_array_equal(one.T[0], many.T[j])


def test_surface_roots_of_all_lanes_at_once_equal_each_lane_alone():
    """The kernel solves the surface equation alpha x + a4 x^4 = rhs of all its lanes in one interleaved
    Newton iteration. Each lane's root must equal the one-lane iteration's bit for bit (a column never
    depends on its batch), and both must be the polynomial's positive real root from numpy's companion
    matrix eigenvalues (an independent method) to 1e-10 relative (eigenvalue round-off of a quartic whose
    coefficients span ~12 decades). Guesses include zero, negative, far above and far below the root."""
    rng = np.random.default_rng(7)
    n = 3 * _LANES + 5
    a4 = 0.95 * SIGMA * rng.choice([0.5, 1.0, 2.0], n)
    alpha = 10.0 ** rng.uniform(-1.0, 3.0, n)  # C/tau + conductance [W m-2 K-1]
    root = rng.uniform(20.0, 420.0, n)  # [K]
    rhs = alpha * root + a4 * root**4
    guess = root * rng.choice([0.2, 0.98, 1.0, 1.03, 5.0], n)
    guess[:4] = [0.0, -50.0, 1e4, 1e-3]
    x = np.zeros(n)
    act = np.full(n, 2, np.int64)
    st = np.zeros(n, np.int64)
    for a in np.unique(a4):  # one a4 per call, as in the kernel
        m = a4 == a
        xm, am, sm = np.zeros(m.sum()), np.full(m.sum(), 2, np.int64), np.zeros(m.sum(), np.int64)
        _kern._newton_lanes(alpha[m], a, rhs[m], guess[m], xm, am, sm)
        x[m], act[m], st[m] = xm, am, sm
    assert np.all(st == _kern.OK) and np.all(act == 3)
    for j in range(n):
        s1 = np.zeros(1, np.int64)
        assert _kern._newton(alpha[j], a4[j], rhs[j], guess[j], s1, 0) == x[j]
        r = np.roots([a4[j], 0.0, 0.0, alpha[j], -rhs[j]])
        r = r[(np.abs(r.imag) < 1e-9 * np.abs(r)) & (r.real > 0)].real
        assert len(r) == 1 and x[j] == pytest.approx(r[0], rel=1e-10)
