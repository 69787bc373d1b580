"""Inversion of brightness temperatures to density (issue 23): likelihood, recovery, bad input."""

import numpy as np
import pytest

from crater_thermal import instrument as ins
from crater_thermal import inversion as inv
from crater_thermal.errors import ConfigError

DENS = [1100.0, 1300.0, 1500.0, 1700.0]
PAIRS = [(a, b) for i, a in enumerate(DENS) for b in DENS[i:]]
TIMES = np.datetime64("2025-01-01", "ns") + np.arange(48) * np.timedelta64(3600, "s")


def _forward():
    """A smooth synthetic grid (not a replay): night cooling whose rate depends on top and bottom."""
    h = np.arange(48.0)
    T = np.empty((len(PAIRS), 48, 2))
    for p, (t, b) in enumerate(PAIRS):
        for f in range(2):
            T[p, :, f] = 60.0 + 5 * f + 20.0 * np.exp(-h / (10.0 + t / 200.0)) + (b - 1100.0) / 40.0
    return inv.ForwardModel(T, [p[0] for p in PAIRS], [p[1] for p in PAIRS], TIMES)


def _obs(fm, k, top, bottom, inst="diviner_ch7", dwell=10.0):
    y = fm.predict([top], [bottom], TIMES[k], np.zeros(k.size, int))[:, 0]
    return inv.ObservationTable(
        time=TIMES[k],
        facet=np.zeros(k.size, int),
        footprint=np.zeros(k.size, int),
        T_b_K=y,
        dwell_s=np.full(k.size, dwell),
        instrument=inst,
    )


def test_woodbury_equals_dense():
    """The rank-3 Woodbury likelihood equals numpy's dense Gaussian log pdf on the explicit C (1e-9 relative:
    both are double-precision evaluations of the same quantity)."""
    rng = np.random.default_rng(1)
    n, P = 30, 7
    y = 70 + rng.normal(size=n)
    m = 70 + rng.normal(size=(n, P))
    d = rng.uniform(0.1, 2.0, size=(n, P))
    V = rng.normal(size=(n, P, 3))
    ll = inv.log_likelihood(y, m, d, V)
    for p in range(P):
        C = np.diag(d[:, p]) + V[:, p] @ V[:, p].T
        r = y - m[:, p]
        sign, logdet = np.linalg.slogdet(C)
        ref = -0.5 * (r @ np.linalg.solve(C, r) + logdet + n * np.log(2 * np.pi))
        assert ll[p] == pytest.approx(ref, rel=1e-9)
    # one covariance shared by all points (the covariance at the measurements): the factored-once path
    ll1 = inv.log_likelihood(y, m, d[:, :1], V[:, :1])
    C = np.diag(d[:, 0]) + V[:, 0] @ V[:, 0].T
    sign, logdet = np.linalg.slogdet(C)
    for p in range(P):
        r = y - m[:, p]
        ref = -0.5 * (r @ np.linalg.solve(C, r) + logdet + n * np.log(2 * np.pi))
        assert ll1[p] == pytest.approx(ref, rel=1e-9)


def test_noiseless_grid_profile_recovered():
    fm = _forward()
    obs = _obs(fm, np.arange(0, 48, 4), 1300.0, 1500.0)
    post = inv.invert(fm, obs, offset_K=0.5)
    assert tuple(post.map_kg_m3[0]) == (1300.0, 1500.0)
    assert np.all(np.isclose(post.probability.sum(axis=(1, 2)), 1.0))


def test_one_sample_is_degenerate_several_narrow():
    fm = _forward()
    one = inv.invert(fm, _obs(fm, np.array([30]), 1300.0, 1500.0))
    many = inv.invert(fm, _obs(fm, np.arange(0, 48, 3), 1300.0, 1500.0))
    assert one.width_ratio[0, 0] > 0.7  # the top is not constrained by one sample
    assert many.sd_kg_m3[0, 0] < 0.5 * one.sd_kg_m3[0, 0]


@pytest.mark.parametrize(
    "change, words",
    [
        (dict(time=TIMES[:3] + np.timedelta64(100, "D")), "outside the run"),
        (dict(facet=np.array([0, 7, 0])), "not a facet"),
        (dict(T_b_K=np.array([70.0, np.nan, 70.0])), "brightness temperature of sample 1"),
        (dict(T_b_K=np.array([-200.0, 70.0, 70.0])), "wrong units"),
    ],
)
def test_bad_observations_one_line(change, words):
    kw = dict(
        time=TIMES[:3], facet=np.zeros(3, int), footprint=np.zeros(3, int), T_b_K=np.full(3, 70.0), dwell_s=np.ones(3)
    )
    kw.update(change)
    with pytest.raises(ConfigError, match=words) as e:
        inv.ObservationTable(**kw).validate(TIMES, 2)
    assert "\n" not in str(e.value)


def test_mixing_matches_instrument():
    """Two-facet footprint: the forward model's band mixing equals instrument.mixed_band_temperature
    (1e-4 K: the forward model inverts radiance by a log table, rel. error < 1e-6)."""
    fm = _forward()
    band = ins.get_instrument("diviner_ch7").band
    k = np.arange(0, 48, 8)
    fac = np.column_stack([np.zeros(k.size, int), np.ones(k.size, int)])
    w = np.column_stack([np.full(k.size, 0.3), np.full(k.size, 0.7)])
    got = fm.predict([1300.0], [1700.0], TIMES[k], fac, w, band=band)[:, 0]
    p = PAIRS.index((1300.0, 1700.0))
    ref = ins.mixed_band_temperature(fm.T[p, k, 0], fm.T[p, k, 1], 0.3, band)
    assert np.max(np.abs(got - ref)) < 1e-4


def test_model_error_levers_quadratic_grid():
    """On a grid of a known quadratic T = 60 + a(t) x^2 + b(t) y^2 + c x y (x, y: top, bottom in grid steps)
    the leave-one-node-out estimate is analytic: second differences D = 2a, 2b, 2(a + b + c) along top,
    bottom and the diagonal, covariance V V^T = 2 sum_d (D_d / 8)(D_d / 8)^T over the samples (1e-9: float
    round-off). The true bilinear/triangle interpolation error of that function (from ``predict``, against the
    function itself) never exceeds the estimated 1-sigma; a linear function has no model error."""
    h = np.arange(48.0)
    a, b, c = 0.3 * np.exp(-h / 20.0), 0.1 + 0.002 * h, -0.05
    x = lambda rho: (rho - 1100.0) / 200.0  # noqa: E731
    T = np.empty((len(PAIRS), 48, 1))
    for p, (t, bo) in enumerate(PAIRS):
        T[p, :, 0] = 60.0 + a * x(t) ** 2 + b * x(bo) ** 2 + c * x(t) * x(bo)
    fm = inv.ForwardModel(T, [p[0] for p in PAIRS], [p[1] for p in PAIRS], TIMES)
    k = np.arange(0, 48, 3)
    V = fm.model_error_levers(TIMES[k], np.zeros(k.size, int))
    g = np.stack([2 * a[k], 2 * b[k], 2 * (a[k] + b[k] + c)], axis=1) / 8.0
    np.testing.assert_allclose(V @ V.T, 2 * g @ g.T, rtol=1e-9, atol=1e-12)
    sd = np.sqrt(np.sum(V**2, axis=1))
    # points inside cells (full cells and the diagonal's triangles), against the function itself
    pts = [(t, bo) for t in np.arange(1100.0, 1700.1, 50.0) for bo in np.arange(1100.0, 1700.1, 50.0) if t <= bo]
    tops, bots = np.array(pts).T
    pred = fm.predict(tops, bots, TIMES[k], np.zeros(k.size, int))
    exact = 60.0 + a[k][:, None] * x(tops) ** 2 + b[k][:, None] * x(bots) ** 2 + c * x(tops) * x(bots)
    err = np.abs(pred - exact).max(axis=1)
    assert np.all(err > 0.01) and np.all(err <= sd), (err, sd)
    lin = inv.ForwardModel(T * 0 + np.array([x(t) + 2 * x(bo) for t, bo in PAIRS])[:, None, None], *zip(*PAIRS), TIMES)
    assert np.sum(lin.model_error_levers(TIMES[k], np.zeros(k.size, int)) ** 2) < 1e-18  # (n, 0) when exactly 0
