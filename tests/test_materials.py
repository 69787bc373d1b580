"""Regolith and rock property models (crater_thermal.materials)."""

import numpy as np
import pytest

from crater_thermal import materials as mat
from crater_thermal.errors import ProfileError


def test_heat_capacity_reference_values():
    # Hemingway 1973 in J/kg/K (thesis Eq. 7.3 x 1000, the unit erratum); reference values
    # from docs/physics.md (Ledlow 1992 / Robie 1970): 758, 276, 112 J/kg/K; 0.5 J/kg/K is the
    # rounding of those published values.
    assert mat.heat_capacity(300.0) == pytest.approx(757.9, abs=0.5)
    assert mat.heat_capacity(100.0) == pytest.approx(276.0, abs=1.0)
    assert mat.heat_capacity(50.0) == pytest.approx(112.0, abs=1.0)


def test_heat_capacity_clamped_below_20K():
    # the polynomial is negative below ~10.2 K: it is held at its 20 K value
    c20 = mat.heat_capacity(20.0)
    assert c20 > 0
    np.testing.assert_allclose(mat.heat_capacity([1.0, 5.0, 10.0, 19.9]), c20, rtol=0, atol=0)
    assert mat.heat_capacity(21.0) > c20


def test_hayne_heat_capacity_and_shapes():
    c = mat.heat_capacity(np.array([[100.0, 250.0]]), "hayne2017")
    assert c.shape == (1, 2)
    # Hayne et al. 2017 polynomial evaluated by hand: c(250) = 671.75 J/kg/K
    assert c[0, 1] == pytest.approx(671.75, abs=0.01)


def test_enthalpy_is_integral_of_heat_capacity():
    T = np.array([5.0, 20.5, 60.0, 150.0, 390.0])  # not at the 20 K kink of c(T)
    h = 1e-3
    dh = (mat.enthalpy(T + h) - mat.enthalpy(T - h)) / (2 * h)
    # central difference of a smooth polynomial: relative error ~1e-9
    np.testing.assert_allclose(dh, mat.heat_capacity(T), rtol=1e-6)
    assert mat.enthalpy(0.0) == 0.0


def test_conductivity_at_table_points():
    for rho, b0, b3 in mat.TABLE_7_2:
        for T in (40.0, 300.0):
            assert mat.regolith_conductivity(rho, T) == pytest.approx(b0 + b3 * T**3, rel=1e-12)


def test_conductivity_interpolates_linearly_between_table_points():
    rho = 0.5 * (1300.0 + 1640.0)
    T = 200.0
    expect = 0.5 * (mat.regolith_conductivity(1300.0, T) + mat.regolith_conductivity(1640.0, T))
    assert mat.regolith_conductivity(rho, T) == pytest.approx(expect, rel=1e-12)


def test_conductivity_extrapolation_warns_and_follows_end_segment():
    with pytest.warns(mat.DensityExtrapolationWarning):
        k800 = mat.regolith_conductivity(800.0, 0.0)
    # b0 slope of the first segment: (0.985e-3 - 0.922e-3) / 340 per kg/m3
    assert k800 == pytest.approx(0.922e-3 - 500.0 * 0.063e-3 / 340.0, rel=1e-12)
    with pytest.warns(mat.DensityExtrapolationWarning):
        mat.regolith_conductivity(2000.0, 100.0)
    assert issubclass(mat.DensityExtrapolationWarning, UserWarning)


@pytest.mark.parametrize("rho", [400.0, 3600.0, float("nan")])
def test_conductivity_rejects_impossible_density(rho):
    with pytest.raises(ProfileError, match="500-3500"):
        mat.regolith_conductivity(rho, 100.0)


def test_rock_conductivity_erratum_values():
    # adopted reading: alpha = 3.05e-7 + 4.0e-6/T m2/s (thesis 3.05, 0.040 in 1e-3 cm2/s and cm2 K/s),
    # rho = 3070, Hemingway c(T): numbers stated in materials.py and docs/physics.md
    for T, k_want, inertia_want in ((100.0, 0.292, 497.0), (300.0, 0.741, 1313.0)):
        k = mat.rock_conductivity(T)
        c = mat.heat_capacity(T)
        assert k == pytest.approx((3.05e-7 + 4.0e-6 / T) * 3070 * c, rel=1e-12)
        # the stated values are rounded to 3 digits
        assert k == pytest.approx(k_want, abs=5e-4)
        assert np.sqrt(k * 3070 * c) == pytest.approx(inertia_want, abs=0.5)  # J m-2 K-1 s-1/2


def test_hayne_conductivity():
    # kc is linear in density: ks at rho_s = 1100, kd at rho_d = 1800; k(350 K) = kc (1 + 2.7)
    assert mat.regolith_conductivity(1100.0, 0.0, "hayne2017") == pytest.approx(7.4e-4, rel=1e-12)
    assert mat.regolith_conductivity(1800.0, 350.0, "hayne2017") == pytest.approx(3.4e-3 * 3.7, rel=1e-12)


def test_coefficient_layout_reproduces_models():
    T = np.array([30.0, 120.0, 380.0])
    b0, b3, e0, e1 = mat.conductivity_coefficients(np.full(3, 3070.0), "rock")
    k = b0 + b3 * T**3 + mat.heat_capacity(T) * (e0 + e1 / T)
    np.testing.assert_allclose(k, mat.rock_conductivity(T), rtol=1e-12)
    b0, b3, e0, e1 = mat.conductivity_coefficients(np.full(3, 1500.0), "regolith")
    np.testing.assert_allclose(b0 + b3 * T**3, mat.regolith_conductivity(1500.0, T), rtol=1e-12)
    assert np.all(e0 == 0) and np.all(e1 == 0)


def test_unknown_property_set_and_constant_set():
    with pytest.raises(ProfileError, match="property_set"):
        mat.heat_capacity(100.0, "moon")
    cs = mat.constant_set(k=0.01, rho=1500.0, c=600.0)
    assert mat.heat_capacity(5.0, cs) == 600.0
    with pytest.raises(ProfileError, match="k=-1"):
        mat.constant_set(k=-1, rho=1.0, c=1.0)
