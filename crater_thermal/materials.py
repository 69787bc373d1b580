"""Thermophysical properties of lunar regolith and rock (SI units).

Two named property sets (:data:`PROPERTY_SETS`):

``"apollo"`` (default, the thesis model, chapter 7.1.2)
    * heat capacity: Hemingway et al. (1973) polynomial, ``c(T) = 1000 * (-2.3173e-2 + 2.1270e-3 T
      + 1.5009e-5 T^2 - 7.3699e-8 T^3 + 9.6552e-11 T^4)`` [J kg-1 K-1]. **Erratum:** the thesis
      prints the bracket in J kg-1 K-1; it is in J g-1 K-1 (c(300 K) = 758, matching Robie 1970).
      The fit is for 90-300 K and turns negative below ~10 K, so it is evaluated at
      ``max(T, 20 K)`` (:data:`C_T_MIN`).
    * regolith conductivity (thesis Table 7.2, Fountain & West 1970): ``k = b0(rho) + b3(rho) T^3``
      with b0, b3 piecewise linear in density through 1300, 1640, 1970 kg m-3 and extrapolated
      linearly from the end segments (:class:`DensityExtrapolationWarning` outside 1300-1970,
      :class:`~crater_thermal.errors.ProfileError` outside 500-3500).
    * rock (3070 kg m-3): ``k = alpha(T) rho c(T)``, ``alpha = d0 + d1 / T`` (thesis Eq. 7.5).
      **Erratum / reading:** the thesis prints d0 = 3.05 m2 s-1 and d1 = 0.040 m2 K s-1 (1e6-1e7 too
      large for rock) and cites measurements of returned Apollo rocks in vacuum. That law has the form
      of the fits of Fujii & Osako (1973, Earth Planet. Sci. Lett. 18, 65-71: thermal diffusivity of
      lunar rocks under atmospheric and vacuum conditions), ``kappa = A + B / T (+ C T^3)`` in cgs units,
      whose coefficients are of order A ~ 1e-3 cm2 s-1 and B ~ 1 cm2 K s-1 (their basalt in vacuum, as
      used by other codes: A = 3.03e-3 cm2 s-1, B = 1.30 cm2 K s-1). The thesis does not name its
      sample. We read its 3.05 as A in 1e-3 cm2 s-1 and 0.040 as B in cm2 K s-1 and convert both to SI
      the same way (cm2 = 1e-4 m2): d0 = 3.05e-3 cm2 s-1 = 3.05e-7 m2 s-1, d1 = 0.040 cm2 K s-1 =
      4.0e-6 m2 K s-1. With c(T) above this gives k = 0.29 W m-1 K-1 and thermal inertia
      sqrt(k rho c) = 497 J m-2 K-1 s-1/2 at 100 K, k = 0.74 and 1313 at 300 K; the Apollo 17 breccia
      70161 measures 2.9-3.6e-7 m2 s-1, 0.74 W m-1 K-1 and 1231 J m-2 K-1 s-1/2 at 300 K (Cheng et al.
      2025, Int. J. Thermophys.). (Until issue 12, d1 was 4.0e-5, a factor 1e-3 with no unit behind it:
      k = 0.60 / 1.02 W m-1 K-1 at 100 / 300 K. Reading both numbers in 1e-3 cm2 units instead, d1 =
      4e-9, would give k = 0.26 / 0.71: the T-dependence is a small term either way.)

``"hayne2017"`` (Hayne et al. 2017, JGR Planets 122)
    * heat capacity ``c = -3.6125 + 2.7431 T + 2.3616e-3 T^2 - 1.2340e-5 T^3 + 8.9093e-9 T^4``
      (also evaluated at ``max(T, 20 K)``).
    * conductivity ``k = kc (1 + chi (T / 350 K)^3)``, chi = 2.7. Their contact conductivity
      kc(z) = kd - (kd - ks) exp(-z/H) has the same depth shape as their density
      rho(z) = rho_d - (rho_d - rho_s) exp(-z/H) (rho_s = 1100, rho_d = 1800 kg m-3,
      ks = 7.4e-4, kd = 3.4e-3 W m-1 K-1, H = 0.06 m), so kc is the linear function of density
      ``kc(rho) = ks + (kd - ks) (rho - rho_s) / (rho_d - rho_s)``; this set uses that relation
      for any density profile (the ``"hayne2017"`` profile of :mod:`crater_thermal.thermal`
      reproduces their model exactly). Their emissivity (0.95) stays a solver argument.
    * rock as in ``"apollo"`` but with this heat capacity.

Every regolith conductivity here has the form ``k = b0 + b3 T^3``; rock adds
``rho c(T) (d0 + d1 / T)``. One per-cell layout (b0, b3, rho d0, rho d1) therefore serves all
materials; :func:`conductivity_coefficients` returns it and the conduction kernel evaluates it.
A third, analytic-test set is made by :func:`constant_set` (constant k, rho, c).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from crater_thermal.constants import ROCK_DENSITY
from crater_thermal.errors import ProfileError
from crater_thermal.profiles import DENSITY_LIMITS, HAYNE_RHO_D, HAYNE_RHO_S, check_density_limits

__all__ = [
    "PROPERTY_SETS",
    "PropertySet",
    "DensityExtrapolationWarning",
    "get_property_set",
    "constant_set",
    "heat_capacity",
    "regolith_conductivity",
    "rock_conductivity",
    "conductivity_coefficients",
    "enthalpy",
    "TABLE_7_2",
    "DENSITY_LIMITS",
    "TABLE_RANGE",
    "C_T_MIN",
    "ROCK_D0",
    "ROCK_D1",
]

#: Temperature [K] below which heat-capacity polynomials are held constant (fit range starts ~90 K;
#: the Hemingway polynomial is negative below ~10.2 K).
C_T_MIN = 20.0

#: Thesis Table 7.2: density [kg m-3], b0 [W m-1 K-1], b3 [W m-1 K-4]
TABLE_7_2 = np.array(
    [
        [1300.0, 0.922e-3, 3.19e-11],
        [1640.0, 0.985e-3, 2.06e-11],
        [1970.0, 1.25e-3, 1.59e-11],
    ]
)
#: Densities [kg m-3] covered by Table 7.2 (outside: DensityExtrapolationWarning)
TABLE_RANGE = (1300.0, 1970.0)

#: Rock diffusivity alpha = ROCK_D0 + ROCK_D1 / T [m2 s-1] (thesis Eq. 7.5; its 3.05 and 0.040 read as
#: 3.05e-3 cm2 s-1 and 0.040 cm2 K s-1, the units of Fujii & Osako 1973's fits; see the module docstring)
ROCK_D0 = 3.05e-7  # [m2 s-1]
ROCK_D1 = 4.0e-6  # [m2 K s-1]

#: Hemingway et al. 1973 polynomial, ascending powers of T, converted to J kg-1 K-1
HEMINGWAY_COEFFS = 1000.0 * np.array([-2.3173e-2, 2.1270e-3, 1.5009e-5, -7.3699e-8, 9.6552e-11])
#: Hayne et al. 2017 polynomial, ascending powers of T [J kg-1 K-1]
HAYNE_COEFFS = np.array([-3.6125, 2.7431, 2.3616e-3, -1.2340e-5, 8.9093e-9])

#: Hayne et al. 2017 conductivity parameters (their profile's HAYNE_RHO_S, HAYNE_RHO_D, HAYNE_H and the
#: density limits DENSITY_LIMITS are in crater_thermal.profiles, re-exported here)
HAYNE_KS, HAYNE_KD = 7.4e-4, 3.4e-3  # [W m-1 K-1]
HAYNE_CHI = 2.7  # [-]
HAYNE_T_REF = 350.0  # [K]


class DensityExtrapolationWarning(UserWarning):
    """A regolith density lies outside 1300-1970 kg m-3: Table 7.2 is extrapolated linearly."""


@dataclass(frozen=True)
class PropertySet:
    """A named set of thermophysical property models.

    Attributes
    ----------
    name : str
    c_coeffs : (5,) float
        Heat capacity polynomial in ascending powers of T [J kg-1 K-1 K^-n], evaluated at
        ``max(T, c_t_min)``.
    c_t_min : float
        [K] lower clamp of the heat-capacity polynomial.
    regolith_model : str
        ``"table72"`` (thesis), ``"hayne2017"`` or ``"constant"``.
    constant : tuple or None
        ``(k [W m-1 K-1], rho [kg m-3], c [J kg-1 K-1])`` for the constant-property test set.
    """

    name: str
    c_coeffs: tuple
    c_t_min: float = C_T_MIN
    regolith_model: str = "table72"
    constant: tuple | None = None

    def heat_capacity(self, T):
        """Specific heat capacity c(T) [J kg-1 K-1] for temperatures ``T`` [K] (any shape)."""
        T = np.maximum(np.asarray(T, dtype=float), self.c_t_min)
        a = self.c_coeffs
        return a[0] + T * (a[1] + T * (a[2] + T * (a[3] + T * a[4])))


PROPERTY_SETS = {
    "apollo": PropertySet("apollo", tuple(HEMINGWAY_COEFFS), C_T_MIN, "table72"),
    "hayne2017": PropertySet("hayne2017", tuple(HAYNE_COEFFS), C_T_MIN, "hayne2017"),
}


def constant_set(k: float, rho: float, c: float) -> PropertySet:
    """A constant-property material (for analytic tests): conductivity ``k`` [W m-1 K-1],
    density ``rho`` [kg m-3] and heat capacity ``c`` [J kg-1 K-1] everywhere, whatever the profile."""
    for name, v in (("k", k), ("rho", rho), ("c", c)):
        if not (np.isfinite(v) and v > 0):
            raise ProfileError(f"constant_set: {name}={v!r} must be a positive finite number")
    return PropertySet("constant", (float(c), 0.0, 0.0, 0.0, 0.0), 0.0, "constant", (float(k), float(rho), float(c)))


def get_property_set(property_set: str | PropertySet = "apollo") -> PropertySet:
    """Look up a property set by name (``"apollo"``, ``"hayne2017"``) or pass one through."""
    if isinstance(property_set, PropertySet):
        return property_set
    try:
        return PROPERTY_SETS[str(property_set)]
    except KeyError:
        raise ProfileError(f"property_set={property_set!r} is unknown; allowed: {sorted(PROPERTY_SETS)}") from None


def heat_capacity(T, property_set: str | PropertySet = "apollo"):
    """Regolith/rock specific heat capacity [J kg-1 K-1].

    Parameters
    ----------
    T : array_like [K]
        Evaluated at ``max(T, 20 K)`` (the polynomials are fits for ~90-350 K).
    property_set : ``"apollo"`` (Hemingway 1973, thesis Eq. 7.3 in J kg-1 K-1) or ``"hayne2017"``.
    """
    return get_property_set(property_set).heat_capacity(T)


def enthalpy(T, property_set: str | PropertySet = "apollo"):
    """Specific enthalpy h(T) = integral_0^T c(max(T', Tmin)) dT' [J kg-1] (exact polynomial integral)."""
    ps = get_property_set(property_set)
    T = np.asarray(T, dtype=float)
    a = ps.c_coeffs
    tm = ps.c_t_min

    def prim(x):
        return x * (a[0] + x * (a[1] / 2 + x * (a[2] / 3 + x * (a[3] / 4 + x * a[4] / 5))))

    c_min = ps.heat_capacity(tm)
    Tc = np.maximum(T, tm)
    return np.where(T <= tm, c_min * T, c_min * tm + prim(Tc) - prim(tm))


def check_density(rho, name: str = "density", warn: bool = True) -> None:
    """Raise ProfileError outside 500-3500 kg m-3; warn (DensityExtrapolationWarning) outside
    the Table 7.2 range 1300-1970 kg m-3 when ``warn``."""
    check_density_limits(rho, name)
    r = np.atleast_1d(np.asarray(rho, dtype=float))
    if warn:
        out = (r < TABLE_RANGE[0]) | (r > TABLE_RANGE[1])
        if np.any(out):
            warnings.warn(
                f"{name}={r[out][0]:.0f} kg/m3 is outside Table 7.2 "
                f"({TABLE_RANGE[0]:.0f}-{TABLE_RANGE[1]:.0f} kg/m3): conductivity "
                "extrapolated linearly",
                DensityExtrapolationWarning,
                stacklevel=3,
            )


def _table72_b(rho):
    """(b0, b3) for densities ``rho`` [kg m-3]: piecewise linear, linear extrapolation at the ends."""
    rho = np.asarray(rho, dtype=float)
    d, b0, b3 = TABLE_7_2.T
    seg = np.clip(np.searchsorted(d, rho) - 1, 0, len(d) - 2)
    w = (rho - d[seg]) / (d[seg + 1] - d[seg])
    return b0[seg] + w * (b0[seg + 1] - b0[seg]), b3[seg] + w * (b3[seg + 1] - b3[seg])


def hayne_kc(rho):
    """Hayne et al. 2017 contact conductivity as a function of density [W m-1 K-1]."""
    rho = np.asarray(rho, dtype=float)
    return HAYNE_KS + (HAYNE_KD - HAYNE_KS) * (rho - HAYNE_RHO_S) / (HAYNE_RHO_D - HAYNE_RHO_S)


def conductivity_coefficients(
    rho, material: str = "regolith", property_set: str | PropertySet = "apollo", warn: bool = False
):
    """Per-cell coefficients of ``k(T) = b0 + b3 T^3 + c(T) (e0 + e1 / T)`` [SI].

    Parameters
    ----------
    rho : array_like [kg m-3]
    material : ``"regolith"`` or ``"rock"``
    property_set : name or PropertySet

    Returns
    -------
    b0 [W m-1 K-1], b3 [W m-1 K-4], e0 = rho d0 [kg m-1 s-1], e1 = rho d1 [kg m-1 s-1 K] :
    arrays like ``rho`` (e0, e1 nonzero for rock only; times c(T) [J kg-1 K-1] they give W m-1 K-1)
    """
    ps = get_property_set(property_set)
    rho = np.asarray(rho, dtype=float)
    z = np.zeros_like(rho)
    if ps.regolith_model == "constant":
        return z + ps.constant[0], z, z, z
    if material == "rock":
        return z, z, rho * ROCK_D0, rho * ROCK_D1
    if material != "regolith":
        raise ProfileError(f"material={material!r} is unknown; allowed: 'regolith', 'rock'")
    check_density(rho, warn=warn and ps.regolith_model == "table72")
    if ps.regolith_model == "hayne2017":
        kc = hayne_kc(rho)
        return kc, kc * HAYNE_CHI / HAYNE_T_REF**3, z, z
    b0, b3 = _table72_b(rho)
    return b0, b3, z, z


def regolith_conductivity(rho, T, property_set: str | PropertySet = "apollo"):
    """Regolith thermal conductivity k(rho, T) [W m-1 K-1].

    ``"apollo"``: thesis Eq. 7.4, ``b0(rho) + b3(rho) T^3`` (Table 7.2, piecewise linear in
    density, extrapolated linearly with a :class:`DensityExtrapolationWarning` outside 1300-1970).
    ``"hayne2017"``: ``kc(rho) (1 + 2.7 (T/350)^3)`` (no Table 7.2 warning).
    Both: ProfileError outside 500-3500 kg m-3.

    Parameters
    ----------
    rho : array_like [kg m-3]; T : array_like [K] (broadcast together)
    """
    b0, b3, _, _ = conductivity_coefficients(rho, "regolith", property_set, warn=True)
    T = np.asarray(T, dtype=float)
    return b0 + b3 * T**3


def rock_conductivity(T, property_set: str | PropertySet = "apollo", rho: float = ROCK_DENSITY):
    """Rock conductivity ``k = (d0 + d1/T) rho c(T)`` [W m-1 K-1], T [K] (thesis Eq. 7.5 with the
    unit erratum d0 = 3.05e-7 m2 s-1, d1 = 4.0e-5 m2 K s-1)."""
    T = np.asarray(T, dtype=float)
    ps = get_property_set(property_set)
    return (ROCK_D0 + ROCK_D1 / T) * rho * ps.heat_capacity(T)
