"""Allowed values of user inputs: the names and spans that case files and the command line may use.

Each tuple here belongs to the module that implements it (named in its comment); that module
imports it from here and re-exports it, so ``illumination.LIMB_DARKENING_LAWS`` and
``choices.LIMB_DARKENING_LAWS`` are the same object. The lists live in this small base module
(imports nothing from crater_thermal but nothing heavy either) so that :mod:`crater_thermal.config`,
which sits in the base layer, can validate a case file without importing the physics modules
(and skyfield, numba, embreex with them). ``tests/test_choices.py`` checks that every owning
module implements exactly the names listed here.

To add a choice: add the name here and implement it in the owning module; the case schema
(:data:`crater_thermal.config.SCHEMA`) and cases/README.md pick it up.
"""

import numpy as np

__all__ = [
    "CRATER_KINDS",
    "HEIGHT_KINDS",
    "LENGTH_UNITS",
    "SPINUP_MODES",
    "SPINUP_IR_METHODS",
    "IR_COUPLING_SCHEMES",
    "OUTPUT_COMPRESSIONS",
    "PROPERTY_SETS",
    "LIMB_DARKENING_LAWS",
    "ALBEDO_MODELS",
    "SCATTERING_METHODS",
    "VIEW_FACTOR_METHODS",
    "MOON_FRAMES",
    "SUN_CORRECTIONS",
    "SUN_METHODS",
    "EPHEMERIS_START",
    "EPHEMERIS_END",
    "DE421_LIBRATION_START",
    "DE421_LIBRATION_END",
    "ephemeris_span",
]

#: Terrain kinds (simulate.case_mesh; geometry or terrain builds each): idealized crater, flat plain, mesh
#: file, a site of a digital elevation model.
CRATER_KINDS = ("crater", "flat", "mesh", "dem")
#: How DEM pixel values are read (terrain): auto-detect (height or radius), height above the reference
#: sphere, radius from the Moon's centre, or "tangent": the coordinate along the up axis of a Cartesian
#: frame tangent to the sphere at the projection's origin (curvature applied; never auto-detected).
HEIGHT_KINDS = ("auto", "height", "radius", "tangent")
#: Length units a DEM's x/y coordinates or pixel values may be declared in (terrain overrides).
LENGTH_UNITS = ("m", "km")
#: Spin-up procedures (runner.run_case).
SPINUP_MODES = ("periodic", "fixed")
#: IR exchange during a periodic spin-up: "coupled" (every step, as the record), "lagged" (each window
#: with the IR series of the previous one, the first with each facet's IR held a day at a time), "auto"
#: (simulate.spinup_ir_method: lagged on large meshes).
SPINUP_IR_METHODS = ("auto", "coupled", "lagged")
#: How a coupled step gets the IR at its end (radiosity.CoupledStepper): extrapolated from the exact IR of
#: the two previous samples (one conduction solve per step), or predictor-corrector (two); or "relaxed":
#: waveform relaxation over windows of samples (crater_thermal.waveform; what a distributed run uses).
IR_COUPLING_SCHEMES = ("extrapolated", "predictor", "relaxed")
#: Lossless compression of run.nc's (time, facet) series (crater_thermal.io.SERIES_COMPRESSION): "zlib"
#: (level 1 after the byte shuffle: any netCDF-4 reader), "blosc_lz4" (7-8x faster to write and 8x faster
#: to read by facet, ~9 % larger; an HDF5 plugin filter that netCDF4's wheels carry and h5py, NCO or
#: MATLAB without the plugin cannot read).
OUTPUT_COMPRESSIONS = ("zlib", "blosc_lz4")
#: Thermophysical property sets (materials.PROPERTY_SETS has one PropertySet per name).
PROPERTY_SETS = ("apollo", "hayne2017")
#: Limb-darkening laws of the Sun's disk (illumination.LIMB_DARKENING_COEFFS has one law per name).
LIMB_DARKENING_LAWS = ("linear", "quadratic", "neckel_labs", "uniform")
#: Albedo of direct sunlight (illumination.direct_albedo): constant, or A(i) of Hayne et al. (2017).
ALBEDO_MODELS = ("constant", "hayne2017")
#: Methods for the scattered sunlight (radiosity).
SCATTERING_METHODS = ("exact", "bounces")
#: View-factor operators (vfoperator): by facet count, exact sparse matrix, compressed.
VIEW_FACTOR_METHODS = ("auto", "exact", "compressed")
#: Moon orientation models (ephemeris.moon_rotation).
MOON_FRAMES = ("iau2009", "de421")
#: Sun-direction corrections (ephemeris.sun_position_moon_fixed).
SUN_CORRECTIONS = ("apparent", "light_time", "geometric")
#: Direct-sunlight methods (simulate; horizons.SUN_METHODS): the ray-traced sampled disk
#: (illumination.direct_irradiance, the reference) or horizon maps (horizons.direct_irradiance_horizon).
SUN_METHODS = ("rays", "horizon")

#: First usable instant (UTC) of the ephemeris (ephemeris). DE421 spans JD 2414864.5 to 2471184.5
#: TDB (1899-07-29 to 2053-10-09); one day is kept as a margin for the light time (~499 s) and
#: TT-UTC (up to ~70 s). tests/test_ephemeris.py checks it against the segments of de421.bsp.
EPHEMERIS_START = np.datetime64("1899-07-30T00:00:00", "ns")
#: Last usable instant (UTC), see :data:`EPHEMERIS_START`.
EPHEMERIS_END = np.datetime64("2053-10-08T00:00:00", "ns")
#: Span of ``moon_pa_de421_1900-2050.bpc`` (UTC, with a one-day margin), for ``moon_frame = "de421"``.
DE421_LIBRATION_START = np.datetime64("1900-01-02T00:00:00", "ns")
DE421_LIBRATION_END = np.datetime64("2049-12-31T00:00:00", "ns")


def ephemeris_span(moon_frame: str = "iau2009"):
    """Usable time span (UTC) for a Moon frame and a description of its source.

    Parameters
    ----------
    moon_frame : {"iau2009", "de421"}

    Returns
    -------
    start, end : numpy.datetime64[ns]
    what : str
        e.g. ``"DE421 (de421.bsp)"``.
    """
    if moon_frame == "de421":
        return (
            max(EPHEMERIS_START, DE421_LIBRATION_START),
            min(EPHEMERIS_END, DE421_LIBRATION_END),
            "DE421 with the moon_pa_de421_1900-2050.bpc librations",
        )
    return EPHEMERIS_START, EPHEMERIS_END, "DE421 (de421.bsp)"
