"""Physical constants and thesis defaults, SI units, each with its source.

Every value here is a *default*: functions take it as a keyword argument so
that users can override it. See ``docs/physics.md``.
"""

import scipy.constants as _sc

#: Stefan-Boltzmann constant [W m-2 K-4] (CODATA 2018, scipy.constants)
SIGMA = _sc.Stefan_Boltzmann
#: Astronomical unit [m] (IAU 2012 resolution B2)
AU = _sc.astronomical_unit
#: Solar constant at 1 au [W m-2] (Kopp & Lean 2011; docs/physics.md)
SOLAR_CONSTANT = 1361.0
#: Nominal solar radius [m] (IAU 2015 resolution B3)
SUN_RADIUS = 695_700e3
#: Mean lunar radius [m] (IAU WGCCRE 2009)
MOON_RADIUS = 1_737_400.0
#: Synodic month, mean length of a lunar day [s]
LUNAR_DAY = 29.530589 * 86400.0
#: Seconds per (Julian) day [s]
DAY = 86400.0
#: Julian year [s]
YEAR = 365.25 * DAY

#: Bond albedo of regolith [-] (thesis 7.1.2)
ALBEDO = 0.12
#: Infrared emissivity of regolith [-] (thesis 7.1.2; Hayne et al. 2017 use 0.95)
EMISSIVITY = 0.98
#: Geothermal heat flux at 2 m [W m-2] (thesis; preliminary Apollo 15 value)
GEOTHERMAL_FLUX = 0.033
#: Depth of the conduction column [m] (thesis 7.1.2)
COLUMN_DEPTH = 2.0
#: Thickness of the top density layer [m] (thesis 7.1.2)
TOP_LAYER_THICKNESS = 0.02
#: Nominal two-layer profile, top/bottom densities [kg m-3] (thesis 7.2)
NOMINAL_PROFILE = (1300.0, 1800.0)
#: Loose two-layer profile, top/bottom densities [kg m-3] (thesis 7.2)
LOOSE_PROFILE = (800.0, 1100.0)
#: Density of rock [kg m-3] (thesis 7.1.2)
ROCK_DENSITY = 3070.0
#: Incidence-dependent albedo A(i) = A0 + a (i / 45 deg)^3 + b (i / 90 deg)^8, coefficients a, b [-]
#: (Keihm 1984 form; Hayne et al. 2017, JGR Planets 122, 2371, Appendix A: a = 0.06, b = 0.25)
HAYNE2017_ALBEDO_A = 0.06
HAYNE2017_ALBEDO_B = 0.25
