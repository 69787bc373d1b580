"""Case files: TOML in, frozen dataclasses out, validated at the edge.

A case file describes one simulation. Every key is declared once, in :data:`SCHEMA` below (one
:class:`Key` per line: section, name, type, default, unit, allowed range or values, meaning). From
that table come

* the validation and defaults of :func:`load_case` / :func:`loads_case`: unknown sections or keys,
  wrong types and out-of-range values raise :class:`~crater_thermal.errors.ConfigError` with one line
  naming the key, the value and what is allowed; dates outside the ephemeris (including the spin-up
  window) raise :class:`~crater_thermal.errors.EphemerisRangeError` naming the key;
* the fields of the section dataclasses (:class:`Crater`, :class:`Location`, ... ; the field names
  are the TOML key names, units in the names; SI conveniences are properties such as
  ``Case.flux_step_s`` or ``Period.spinup_s``);
* the key table of ``cases/README.md`` (``python -m crater_thermal.config --markdown`` prints it,
  ``--update cases/README.md`` rewrites it; ``tests/test_config.py`` checks the README matches).

Allowed names (limb-darkening laws, property sets, ...) are declared in :mod:`crater_thermal.choices`
and re-exported by the modules that implement them; density profiles are checked with the parser of
:mod:`crater_thermal.profiles`, the one the thermal model uses. So this module imports nothing above
the base layer (no ephemeris, skyfield, numba): the ephemeris's usable span is data in ``choices``.

Adding a key
------------
Add one line to :data:`SCHEMA`, e.g.::

    Key("surface", "roughness_deg", "float", 0.0, "mean slope of unresolved roughness", unit="deg", lo=0, hi=45),

and regenerate the README table (``python -m crater_thermal.config --update cases/README.md``). The
section's dataclass gets the field ``roughness_deg`` (the schema default as its default), the loader
validates it, the README documents it. Key types: ``str``, ``choice`` (with ``choices=``), ``float``,
``int`` (with ``lo``/``hi``, ``lo_open``/``hi_open``, ``unit``), ``bool``, ``date``, ``file`` /
``folder`` (paths relative to the case file, must exist), ``profile`` (a density profile label),
``profiles`` (a list of them), ``grid`` (a density grid). A key that applies only to some values of
another key of its section says so with ``only=("kind", ("crater",))``: it is refused elsewhere,
and if it has no default it is required where it applies. A default that depends on other keys is a
function of the values read so far (``lo`` and ``hi`` may be too); give ``default_doc`` /
``allowed_doc`` for the README then. Checks across keys go into :data:`_SECTION_CHECKS` or
:func:`_check_case`.

Adding a section: an entry in :data:`SECTIONS`, a class decorated with ``@_section("name")`` (its
fields come from the schema) and a field of that class in :class:`Case`.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import re
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional, Tuple

import numpy as np

from crater_thermal import choices, profiles
from crater_thermal.constants import (
    ALBEDO,
    EMISSIVITY,
    GEOTHERMAL_FLUX,
    HAYNE2017_ALBEDO_A,
    HAYNE2017_ALBEDO_B,
    SOLAR_CONSTANT,
    YEAR,
)
from crater_thermal.errors import ConfigError, EphemerisRangeError, ProfileError

__all__ = [
    "Crater",
    "Location",
    "Period",
    "Steps",
    "Surface",
    "Sun",
    "Scattering",
    "Replay",
    "Output",
    "Case",
    "Key",
    "SCHEMA",
    "SECTIONS",
    "REQUIRED",
    "load_case",
    "loads_case",
    "dump_toml",
    "schema_markdown",
    "check_site_centre",
    "CRATER_KINDS",
    "SPINUP_MODES",
    "PROPERTY_SETS",
    "LIMB_DARKENING_LAWS",
    "SCATTERING_METHODS",
    "MOON_FRAMES",
    "SUN_CORRECTIONS",
]

# the allowed names, re-exported for compatibility (declared in crater_thermal.choices)
CRATER_KINDS = choices.CRATER_KINDS
SPINUP_MODES = choices.SPINUP_MODES
PROPERTY_SETS = choices.PROPERTY_SETS
LIMB_DARKENING_LAWS = choices.LIMB_DARKENING_LAWS
SCATTERING_METHODS = choices.SCATTERING_METHODS
MOON_FRAMES = choices.MOON_FRAMES
SUN_CORRECTIONS = choices.SUN_CORRECTIONS

_MIN_PERIODIC_DAYS = 29.5  # [d] shortest periodic spin-up window (about one synodic month)


# ---------------------------------------------------------------- the schema
class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


#: Default of a key that has none: the case file must give it.
REQUIRED = _Required()
_DERIVE = object()


@dataclass(frozen=True)
class Key:
    """One key of a case file.

    Attributes
    ----------
    section : str
        TOML table (``""`` for the top level).
    name : str
        Key name (units in the name: ``lat_deg``, ``flux_step_hours``); also the dataclass field.
    type : str
        ``str``, ``choice``, ``float``, ``int``, ``bool``, ``date``, ``file``, ``folder``, ``profile``,
        ``profiles`` or ``grid`` (see the module docstring).
    default : value, :data:`REQUIRED`, or callable(values) -> value
        Used when the key is absent. A callable gets the section's values read so far (a mapping with
        ``given(name)``, true when the file has that key).
    doc : str
        Meaning (README column "meaning").
    unit : str
        Unit of numbers, for messages and the README.
    lo, hi : number, callable(values) -> number, or None
        Allowed range (inclusive unless ``lo_open`` / ``hi_open``).
    choices : tuple of str
        Allowed values of a ``choice`` key.
    only : (key, values) or None
        The key applies only when that other key of the section has one of ``values``.
    default_doc, allowed_doc : str or None
        README text for a computed default or range.
    field : bool
        False for an input-only key that is not a dataclass field (``period.spinup_days``).
    field_default : value
        The dataclass field's default when it differs from ``default`` (a computed default, or the
        value of a key that does not apply).
    """

    section: str
    name: str
    type: str
    default: Any = None
    doc: str = ""
    unit: str = ""
    lo: Any = None
    hi: Any = None
    lo_open: bool = False
    hi_open: bool = False
    choices: Tuple[str, ...] = ()
    only: Optional[Tuple[str, Tuple[str, ...]]] = None
    default_doc: Optional[str] = None
    allowed_doc: Optional[str] = None
    field: bool = True
    field_default: Any = _DERIVE

    @property
    def dotted(self) -> str:
        return f"{self.section}.{self.name}" if self.section else self.name

    @property
    def dataclass_default(self) -> Any:
        """Default of the dataclass field (:data:`REQUIRED`: the field has none)."""
        if self.field_default is not _DERIVE:
            return self.field_default
        if self.only is not None or callable(self.default):
            return None
        return self.default


def _spinup_limits(v) -> Tuple[float, float]:
    """Allowed spin-up window [yr]: a periodic state needs at least one lunar day of forcing."""
    if v["spinup"] == "periodic":
        return _MIN_PERIODIC_DAYS * 86400.0 / YEAR, 50.0
    return 0.0, 300.0


_YR_TO_D = YEAR / 86400.0
_DATE_SPAN = (
    f"{np.datetime_as_string(choices.EPHEMERIS_START, unit='D')} … "
    f"{np.datetime_as_string(choices.EPHEMERIS_END, unit='D')} UTC"
)
_RHO = profiles.DENSITY_LIMITS
_PROFILE_ALLOWED = f'`"TOP/BOTTOM"` ({_RHO[0]:g} … {_RHO[1]:g} kg m⁻³, top ≤ bottom), `"RHO"`, `"rock"`, `"hayne2017"`'
K = Key

#: Every key of a case file, in file order within each section.
SCHEMA: Tuple[Key, ...] = (
    K(
        "",
        "name",
        "str",
        lambda v: v.default_name,
        "case name, labels outputs",
        default_doc="file stem",
        allowed_doc="non-empty",
        field=False,
    ),
    K("", "description", "str", "", "free text", field=False),
    # [crater]
    K(
        "crater",
        "kind",
        "choice",
        lambda v: "mesh" if v.given("mesh") else "crater",
        "idealized crater (thesis Table 7.1, Pike 1977) / flat horizontal surface, no crater (Fig. 7.9) / "
        "a mesh file / a site of a DEM (`dem` and the keys after it)",
        choices=choices.CRATER_KINDS,
        default_doc='`"crater"` (`"mesh"` if `mesh` is given)',
        field_default="crater",
    ),
    K(
        "crater",
        "diameter_km",
        "float",
        REQUIRED,
        "rim diameter",
        unit="km",
        lo=0.0,
        hi=15.0,
        lo_open=True,
        only=("kind", ("crater",)),
    ),
    K("crater", "facets", "int", 502, "number of triangles", lo=20, hi=1_000_000, only=("kind", ("crater",))),
    K(
        "crater",
        "surround_km",
        "float",
        0.0,
        "width of flat plain meshed around the rim",
        unit="km",
        lo=0.0,
        hi=100.0,
        only=("kind", ("crater",)),
        field_default=0.0,
    ),
    K(
        "crater",
        "mesh",
        "file",
        REQUIRED,
        "`.ply`/`.obj`/`.stl` in metres, x east, y north, z up; **relative to the case file**",
        only=("kind", ("mesh",)),
    ),
    K(
        "crater",
        "flip",
        "bool",
        False,
        "reverse every facet's winding (a mesh file whose normals point down, which is refused otherwise)",
        only=("kind", ("mesh",)),
        field_default=False,
    ),
    K(
        "crater",
        "dem",
        "file",
        REQUIRED,
        "digital elevation model: GeoTIFF, PDS3 `.LBL`/`.IMG` (LOLA `LDEM_*`), any "
        "GDAL raster with a projected lunar CRS; **relative to the case file**",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "center_lat_deg",
        "float",
        None,
        "site centre latitude (as `mesh dem --center-lat`); must "
        "equal `location.lat_deg`, the frame of the Sun vectors",
        unit="deg",
        lo=-90.0,
        hi=90.0,
        default_doc="`location.lat_deg`",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "center_lon_deg",
        "float",
        None,
        "site centre east longitude; must equal `location.lon_deg`",
        unit="deg",
        lo=-360.0,
        hi=360.0,
        default_doc="`location.lon_deg`",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "radius_km",
        "float",
        REQUIRED,
        "radius of the analysed (inner) region about the centre",
        unit="km",
        lo=0.0,
        hi=500.0,
        lo_open=True,
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "resolution_m",
        "float",
        None,
        "facet edge in the inner region (equilateral lattice; ~7.3 (radius/edge)² facets)",
        unit="m",
        lo=0.0,
        hi=1e5,
        lo_open=True,
        default_doc="DEM pixel or ~10,000 inner facets, the coarser",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "outer_radius_km",
        "float",
        None,
        "coarser ring out to this radius: shadows and radiation from distant terrain, not analysed",
        unit="km",
        lo=0.0,
        hi=1000.0,
        lo_open=True,
        default_doc="no ring",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "outer_resolution_m",
        "float",
        None,
        "facet edge in the outer ring",
        unit="m",
        lo=0.0,
        hi=1e5,
        lo_open=True,
        default_doc="4 × `resolution_m`",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "height_kind",
        "choice",
        "auto",
        "DEM values are heights above the reference sphere, radii "
        "from the Moon's centre (LOLA: radius = DN·0.5 m + 1737.4 km), or tangent: curvature applied, z in a "
        "Cartesian frame tangent at the projection's origin (python-flux's LOLA `.grd`: ≈ height − r²/2R); "
        "auto: radius if > half the radius, else height",
        choices=choices.HEIGHT_KINDS,
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "crs",
        "str",
        None,
        "CRS of the DEM instead of the file's (a file with none or a wrong one): PROJ string, WKT or "
        'authority code, e.g. `"IAU_2015:30135"` (Moon south polar stereographic, R = 1737.4 km)',
        default_doc="the file's",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "xy_units",
        "choice",
        None,
        "unit of the DEM's x/y coordinates (geotransform), whatever its CRS says",
        choices=choices.LENGTH_UNITS,
        default_doc="the CRS's",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "z_units",
        "choice",
        None,
        "unit of the DEM's pixel values (after scale/offset), whatever its band says",
        choices=choices.LENGTH_UNITS,
        default_doc="the band's unit (m if none)",
        only=("kind", ("dem",)),
    ),
    K(
        "crater",
        "max_facets",
        "int",
        2_000_000,
        "refuse a site estimated above this many facets",
        lo=1,
        hi=100_000_000,
        only=("kind", ("dem",)),
    ),
    # [location]
    K(
        "location",
        "lat_deg",
        "float",
        REQUIRED,
        "planetocentric latitude of the crater centre",
        unit="deg",
        lo=-90.0,
        hi=90.0,
    ),
    K("location", "lon_deg", "float", 0.0, "east longitude", unit="deg", lo=-360.0, hi=360.0),
    # [period]
    K(
        "period",
        "start",
        "date",
        REQUIRED,
        'first recorded instant (`"2019-01-01"`, `"2019-01-01T04:00:00"`; UTC)',
        allowed_doc=_DATE_SPAN,
    ),
    K("period", "end", "date", REQUIRED, "last recorded instant", allowed_doc="> `start`, in range"),
    K(
        "period",
        "spinup",
        "choice",
        "periodic",
        "periodic: converge to the periodic steady state of the "
        "forcing over the `spinup_years` before `start`; fixed: simulate that window once (thesis) from "
        "`initial_temperature_K` or the equilibrium estimate",
        choices=choices.SPINUP_MODES,
    ),
    K(
        "period",
        "spinup_years",
        "float",
        lambda v: 1.0 if v["spinup"] == "periodic" else 3.0,
        "spin-up window [years of 365.25 d]",
        unit="yr",
        lo=lambda v: _spinup_limits(v)[0],
        hi=lambda v: _spinup_limits(v)[1],
        default_doc="1.0 (periodic), 3.0 (fixed)",
        allowed_doc="periodic 29.5 d … 50 yr; fixed 0 … 300 yr; the window must start inside the ephemeris",
        field_default=1.0,
    ),
    K(
        "period",
        "spinup_days",
        "float",
        None,
        "alternative to `spinup_years` (give one)",
        unit="d",
        lo=lambda v: _spinup_limits(v)[0] * _YR_TO_D,
        hi=lambda v: _spinup_limits(v)[1] * _YR_TO_D,
        default_doc="—",
        allowed_doc="same, in days",
        field=False,
    ),
    K(
        "period",
        "initial_temperature_K",
        "float",
        None,
        "uniform start (fixed) or first guess (periodic); none = equilibrium estimate",
        unit="K",
        lo=1.0,
        hi=1000.0,
    ),
    K("period", "periodic_tol_K", "float", 0.01, "periodic-state convergence tolerance", unit="K", lo=1e-6, hi=10.0),
    K(
        "period",
        "spinup_ir",
        "choice",
        "auto",
        "IR exchange in the periodic spin-up windows: coupled (every step, as in the record), lagged (each "
        "window driven by the previous window's IR, the first by each facet's IR held a day at a time, in "
        "12-hour steps: one conduction solve per step; converged columns whose IR stays put are skipped), auto "
        "(lagged from 10,000 facets)",
        choices=choices.SPINUP_IR_METHODS,
    ),
    # [steps]
    K(
        "steps",
        "flux_step_hours",
        "float",
        4.0,
        "interval between flux (boundary condition) samples (thesis 4 h)",
        unit="h",
        lo=0.0,
        hi=24.0,
        lo_open=True,
    ),
    K(
        "steps",
        "conduction_step_s",
        "float",
        None,
        "largest conduction sub-step",
        unit="s",
        lo=0.0,
        hi=lambda v: v["flux_step_hours"] * 3600.0,
        lo_open=True,
        default_doc="solver default",
        allowed_doc="0 < dt ≤ flux step [s]",
    ),
    K(
        "steps",
        "ir_coupling",
        "choice",
        "extrapolated",
        "IR at the end of a coupled step: extrapolated in time from the exact IR of the two samples before "
        "(one conduction solve per step), or predictor-corrector (a predictor solve, then the step again "
        "with the predicted IR: two solves), or relaxed (waveform relaxation: every column through a window of "
        "samples with the previous iterate's IR, repeated to 0.001 K; the fully implicit exchange, and the "
        "scheme of a distributed run); docs/model.md: accuracy of each",
        choices=choices.IR_COUPLING_SCHEMES,
    ),
    K(
        "steps",
        "ir_product_samples",
        "int",
        None,
        "extrapolated coupling: samples per exact IR product of the record; with n > 1 the IR of the samples "
        "between is predicted from the last two products and the sunlight the terrain absorbs (columns whose "
        "IR it missed taken again); 1: a product every step; docs/model.md: accuracy",
        lo=1,
        hi=12,
        default_doc="2 from 10,000 facets, 1 below",
    ),
    # [surface]
    K(
        "surface",
        "albedo",
        "float",
        ALBEDO,
        'Bond albedo; with `albedo_model = "hayne2017"` the normal-incidence value A0 (also used for scattered light)',
        lo=0.0,
        hi=1.0,
        hi_open=True,
    ),
    K(
        "surface",
        "albedo_model",
        "choice",
        "constant",
        "albedo of direct sunlight: constant, or Hayne et al. (2017) "
        "A(i) = A0 + a (i/45°)³ + b (i/90°)⁸ (illumination.direct_albedo)",
        choices=choices.ALBEDO_MODELS,
    ),
    K("surface", "albedo_a", "float", HAYNE2017_ALBEDO_A, "coefficient a of the hayne2017 model", lo=0.0, hi=1.0),
    K("surface", "albedo_b", "float", HAYNE2017_ALBEDO_B, "coefficient b of the hayne2017 model", lo=0.0, hi=1.0),
    K("surface", "emissivity", "float", EMISSIVITY, "infrared emissivity", lo=0.0, hi=1.0, lo_open=True),
    K(
        "surface",
        "property_set",
        "choice",
        "apollo",
        "heat capacity / conductivity models",
        choices=choices.PROPERTY_SETS,
    ),
    K(
        "surface",
        "geothermal_flux_W_m2",
        "float",
        GEOTHERMAL_FLUX,
        "heat flux into the bottom of the 2 m column",
        unit="W m-2",
        lo=0.0,
        hi=1.0,
    ),
    K(
        "surface",
        "nominal_profile",
        "profile",
        profiles.NOMINAL_LABEL,
        "density profile of the coupled run",
        allowed_doc=_PROFILE_ALLOWED,
    ),
    # [sun]
    K(
        "sun",
        "limb_darkening",
        "choice",
        "linear",
        "limb-darkening law of the disk",
        choices=choices.LIMB_DARKENING_LAWS,
    ),
    K("sun", "point_sun", "bool", False, "point Sun instead of the extended disk"),
    K("sun", "n_rings", "int", None, "rings of the disk model", lo=1, hi=100, default_doc="illumination default"),
    K(
        "sun",
        "solar_constant_W_m2",
        "float",
        SOLAR_CONSTANT,
        "irradiance at 1 au (scaled by (1 au / r)²)",
        unit="W m-2",
        lo=1000.0,
        hi=2000.0,
    ),
    K(
        "sun",
        "moon_frame",
        "choice",
        "iau2009",
        "Moon orientation model (ephemeris/README.md)",
        choices=choices.MOON_FRAMES,
    ),
    K(
        "sun",
        "moon_kernels",
        "folder",
        None,
        'holds `moon_080317.tf` and `moon_pa_de421_1900-2050.bpc`; required for `"de421"`; relative to the case file',
    ),
    K(
        "sun",
        "correction",
        "choice",
        "apparent",
        "which Sun direction (ephemeris/README.md)",
        choices=choices.SUN_CORRECTIONS,
    ),
    K(
        "sun",
        "method",
        "choice",
        "horizon",
        "direct sunlight: one ray per disk patch, facet and step (the "
        "reference) / horizon map per facet, traced once per mesh and cached (docs/performance.md: cost and accuracy)",
        choices=choices.SUN_METHODS,
    ),
    K(
        "sun",
        "horizon_azimuths",
        "int",
        720,
        "azimuths of the horizon map",
        lo=8,
        hi=4096,
        only=("method", ("horizon",)),
    ),
    # [scattering]
    K(
        "scattering",
        "method",
        "choice",
        "exact",
        "radiosity solve, or a fixed number of bounces (thesis: 3)",
        choices=choices.SCATTERING_METHODS,
    ),
    K("scattering", "n_bounces", "int", 3, 'bounces for `"bounces"`', lo=1, hi=100),
    # [radiation]
    K(
        "radiation",
        "view_factors",
        "choice",
        "auto",
        "exact sparse view-factor matrix, hierarchically compressed "
        "operator, or by facet count (auto: compressed from 10,000 facets on)",
        choices=choices.VIEW_FACTOR_METHODS,
    ),
    K(
        "radiation",
        "tolerance",
        "float",
        1e-3,
        "compressed operator: relative Frobenius error allowed per far block (products come out ~50x more accurate)",
        lo=1e-8,
        hi=0.1,
    ),
    # [replay]
    K(
        "replay",
        "profiles",
        "profiles",
        (),
        "profiles replayed on the saved nominal fluxes",
        allowed_doc="labels as for `nominal_profile`",
    ),
    K(
        "replay",
        "density_grid",
        "grid",
        None,
        'all two-layer profiles on that grid (top ≤ bottom), e.g. `"800:2000:100"`',
        allowed_doc=f'`"LO:HI:STEP"`, {_RHO[0]:g} ≤ LO ≤ HI ≤ {_RHO[1]:g}, STEP > 0, at most '
        f"{profiles.MAX_GRID_DENSITIES} densities [kg m⁻³]",
    ),
    # [output]
    K(
        "output",
        "checkpoint_interval_steps",
        "int",
        0,
        "checkpoint every n flux steps (0: only after the spin-up)",
        lo=0,
        hi=10_000_000,
    ),
    K(
        "output",
        "save_spinup_fluxes",
        "bool",
        True,
        "also store the spin-up window's fluxes, so that replays start exactly as the run did (false: "
        "run.nc and the scratch store hold less: the spin-up's sunlight leaves the store when the start ends)",
    ),
    K(
        "output",
        "chunk_mb",
        "float",
        None,
        "memory for the run's (time, facet) series: sunlight, temperatures "
        "and IR are computed, kept and written in blocks of time samples that fit it, whatever the run's length "
        "and size",
        unit="MB",
        lo=0.01,
        hi=1e6,
        default_doc="256, or blocks of 48 samples above ~116k facets (≤ 4096: 2.2 GB at 1M facets)",
    ),
    K(
        "output",
        "compression",
        "choice",
        "zlib",
        "lossless compression of run.nc's (time, facet) series: zlib (readable by every netCDF-4 tool) or "
        "blosc_lz4 (7-8x faster to write, ~9 % larger; needs the HDF5 blosc plugin to read: netCDF4's pip "
        "wheels carry it, h5py needs hdf5plugin, NCO and MATLAB a plugin path); docs/model.md",
        choices=choices.OUTPUT_COMPRESSIONS,
    ),
)
del K


@dataclass(frozen=True)
class SectionSpec:
    """A TOML table of the case file: its name, whether the file must have it, a README note."""

    name: str
    required: bool = False


#: The sections, in the order they are read and documented.
SECTIONS: Tuple[SectionSpec, ...] = (
    SectionSpec("crater", required=True),
    SectionSpec("location", required=True),
    SectionSpec("period", required=True),
    SectionSpec("steps"),
    SectionSpec("surface"),
    SectionSpec("sun"),
    SectionSpec("scattering"),
    SectionSpec("radiation"),
    SectionSpec("replay"),
    SectionSpec("output"),
)

_ANNOTATIONS = {
    "str": "str",
    "choice": "str",
    "float": "float",
    "int": "int",
    "bool": "bool",
    "date": "np.datetime64",
    "file": "Path",
    "folder": "Path",
    "profile": "str",
    "profiles": "Tuple[str, ...]",
    "grid": "str",
}
_SECTION_CLASSES: dict = {}


def _keys(section: str) -> Tuple[Key, ...]:
    return tuple(k for k in SCHEMA if k.section == section)


def _section(name: str):
    """Class decorator: a frozen dataclass whose fields are the schema's keys of section ``name``."""

    def deco(cls):
        ann = {}
        for key in _keys(name):
            if not key.field:
                continue
            default = key.dataclass_default
            ann[key.name] = _ANNOTATIONS[key.type] if default is not None else f"Optional[{_ANNOTATIONS[key.type]}]"
            if default is not REQUIRED:
                setattr(cls, key.name, default)
        cls.__annotations__ = ann
        lines = [
            f"    {k.name} : {ann[k.name]}" + (f" [{k.unit}]" if k.unit else "") + f"\n        {k.doc}"
            for k in _keys(name)
            if k.field
        ]
        cls.__doc__ = (
            (cls.__doc__ or "").rstrip()
            + "\n\n    Fields (from :data:`SCHEMA`)\n    "
            + "-" * 28
            + "\n"
            + "\n".join(lines)
            + "\n"
        )
        cls = dataclass(frozen=True)(cls)
        _SECTION_CLASSES[name] = cls
        return cls

    return deco


# ---------------------------------------------------------------- dataclasses
# Fields come from SCHEMA (same names, defaults, in schema order); the docstrings say what they hold.
@_section("crater")
class Crater:
    """Terrain of the case: an idealized crater (``kind = "crater"``), flat ground, a mesh file or a site of
    a DEM (meshed by ``terrain.site_mesh``; ``crs``, ``xy_units`` and ``z_units`` override the DEM file's
    metadata). Paths are absolute. The fields, their units and ranges follow."""


@_section("location")
class Location:
    """Crater centre: planetocentric latitude ``lat_deg`` and east longitude ``lon_deg`` [deg]."""


@_section("period")
class Period:
    """Recorded period and spin-up: ``start`` and ``end`` are numpy.datetime64 (UTC, ns); ``spinup_years``
    [yr of 365.25 d] is set also when the file gives ``spinup_days``. The fields, their units and ranges
    follow."""

    @property
    def spinup_s(self) -> float:
        """Spin-up window [s]."""
        return self.spinup_years * YEAR

    @property
    def spinup_start(self) -> np.datetime64:
        """First instant of the spin-up window (UTC, rounded to 1 s)."""
        return self.start - np.timedelta64(int(round(self.spinup_s)), "s")

    @property
    def duration_s(self) -> float:
        """Recorded period length [s]."""
        return float((self.end - self.start) / np.timedelta64(1, "s"))


@_section("steps")
class Steps:
    """Time steps: flux step ``flux_step_hours`` [h], optional largest conduction sub-step
    ``conduction_step_s`` [s], the coupled step's IR scheme ``ir_coupling``, samples per IR product of the
    record ``ir_product_samples``."""

    @property
    def flux_step_s(self) -> float:
        """Flux step [s]."""
        return self.flux_step_hours * 3600.0


@_section("surface")
class Surface:
    """Surface and subsurface properties (see docs/physics.md): albedo, emissivity, property set,
    geothermal flux [W m-2], nominal density profile label."""


@_section("sun")
class Sun:
    """Sun model and ephemeris options."""


@_section("scattering")
class Scattering:
    """Scattered sunlight: exact radiosity or ``n_bounces`` bounces."""


@_section("radiation")
class Radiation:
    """View factors of the radiation exchange: exact sparse matrix or compressed operator."""


@_section("replay")
class Replay:
    """Profiles replayed on the saved nominal fluxes (labels) and an optional density grid."""


@_section("output")
class Output:
    """Output options."""


@dataclass(frozen=True)
class Case:
    """A validated case. Build with :func:`load_case` / :func:`loads_case`.

    Attributes
    ----------
    name : str
    crater, location, period, steps, surface, sun, scattering, radiation, replay, output : sections
    toml_text : str  the case file's original text (stored in outputs)
    path : Path or None  the case file (None for text)
    description : str
    """

    name: str
    crater: Crater
    location: Location
    period: Period
    steps: Steps = Steps()
    surface: Surface = Surface()
    sun: Sun = Sun()
    scattering: Scattering = Scattering()
    radiation: Radiation = Radiation()
    replay: Replay = Replay()
    output: Output = Output()
    toml_text: str = ""
    path: Optional[Path] = None
    description: str = ""

    def replace(self, **changes) -> "Case":
        """``dataclasses.replace`` (no re-validation; prefer :meth:`with_overrides`)."""
        return dataclasses.replace(self, **changes)

    def with_overrides(self, overrides: Mapping[str, Any], name: Optional[str] = None) -> "Case":
        """A re-validated copy with dotted-key overrides.

        Parameters
        ----------
        overrides : mapping
            ``{"location.lat_deg": -80.0, "period.spinup": "fixed", "name": "x"}``;
            a value of None removes the key (back to its default).
        name : str, optional
            New case name.

        Returns
        -------
        Case
            Its ``toml_text`` is the regenerated TOML of the new case (comments
            lost), headed by a comment naming the original and the overrides.
        """
        raw = _strip_derived(tomllib.loads(self.toml_text)) if self.toml_text else {}
        for dotted, value in overrides.items():
            parts = dotted.split(".")
            if len(parts) > 2 or not all(parts):
                raise ConfigError(f"override key {dotted!r} must be 'key' or 'section.key'")
            target = raw if len(parts) == 1 else raw.setdefault(parts[0], {})
            if not isinstance(target, dict):
                raise ConfigError(f"override key {dotted!r}: {parts[0]!r} is not a section")
            if value is None:
                target.pop(parts[-1], None)
            else:
                target[parts[-1]] = str(value) if isinstance(value, Path) else value
        if name is not None:
            raw["name"] = name
        elif "name" not in raw:
            raw["name"] = self.name
        header = "# derived from case {!r} with overrides: {}\n".format(
            self.name, ", ".join(f"{k} = {v!r}" for k, v in overrides.items())
        )
        text = header + dump_toml(raw)
        base = self.path.parent if self.path is not None else None
        return _build_case(raw, text, base_dir=base, path=self.path, default_name=self.name)


def _strip_derived(raw: dict) -> dict:
    return {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}


# ---------------------------------------------------------------- reading one section
def _fmt_range(lo, hi, lo_open=False, hi_open=False, unit=""):
    if lo is None and hi is None:
        s = "any finite number"
    elif hi is None:
        s = f"{'>' if lo_open else '>='} {lo:g}"
    elif lo is None:
        s = f"{'<' if hi_open else '<='} {hi:g}"
    else:
        s = f"{lo:g} {'<' if lo_open else '<='} x {'<' if hi_open else '<='} {hi:g}"
    return s + (f" [{unit}]" if unit else "")


class _Section:
    """Reads one TOML table, remembering which keys were used."""

    def __init__(self, data: Any, name: str, where: str):
        self.where = where
        self.name = name
        if data is None:
            data = {}
        if not isinstance(data, dict):
            self.fail(f"[{name}] must be a table (section), got {type(data).__name__} {data!r}")
        self.data = data
        self.used: set = set()

    def key(self, k: str) -> str:
        return f"{self.name}.{k}" if self.name else k

    def fail(self, msg: str):
        raise ConfigError(f"{self.where}: {msg}")

    def has(self, k: str) -> bool:
        return k in self.data

    def raw(self, k: str, default=None, required=False):
        self.used.add(k)
        if k not in self.data:
            if required:
                self.fail(f"missing required key {self.key(k)}")
            return default
        return self.data[k]

    def number(
        self, k, default=None, lo=None, hi=None, lo_open=False, hi_open=False, unit="", required=False, integer=False
    ):
        v = self.raw(k, default, required)
        if k not in self.data:
            return default
        kind = "an integer" if integer else "a number"
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)):
            self.fail(
                f"{self.key(k)} = {v!r} has the wrong type ({type(v).__name__}); expected {kind}, "
                f"allowed: {_fmt_range(lo, hi, lo_open, hi_open, unit)}"
            )
        if not math.isfinite(v):
            self.fail(f"{self.key(k)} = {v!r} is not finite; allowed: {_fmt_range(lo, hi, lo_open, hi_open, unit)}")
        bad = (lo is not None and (v < lo or (lo_open and v == lo))) or (
            hi is not None and (v > hi or (hi_open and v == hi))
        )
        if bad:
            self.fail(f"{self.key(k)} = {v!r} out of range; allowed: {_fmt_range(lo, hi, lo_open, hi_open, unit)}")
        return int(v) if integer else float(v)

    def boolean(self, k, default):
        v = self.raw(k, default)
        if not isinstance(v, bool):
            self.fail(f"{self.key(k)} = {v!r} has the wrong type ({type(v).__name__}); allowed: true or false")
        return v

    def string(self, k, default=None, required=False):
        v = self.raw(k, default, required)
        if v is None:
            return v
        if not isinstance(v, str):
            self.fail(f"{self.key(k)} = {v!r} has the wrong type ({type(v).__name__}); expected a string")
        return v

    def choice(self, k, options, default):
        v = self.string(k, default)
        if v is None and default is None and not self.has(k):
            return None  # an optional choice left out
        if v not in options:
            self.fail(f"{self.key(k)} = {v!r} is not allowed; allowed: {', '.join(repr(o) for o in options)}")
        return v

    def date(self, k):
        v = self.raw(k, required=True)
        if isinstance(v, _dt.datetime):
            if v.tzinfo is not None:
                v = v.astimezone(_dt.timezone.utc).replace(tzinfo=None)
            v = v.isoformat()
        elif isinstance(v, _dt.date):
            v = v.isoformat()
        if not isinstance(v, str):
            self.fail(
                f"{self.key(k)} = {v!r} has the wrong type ({type(v).__name__}); "
                'expected an ISO 8601 date such as "2019-01-01" or "2019-01-01T04:00:00"'
            )
        s = v.strip()
        if s.endswith(("Z", "z")):
            s = s[:-1]
        try:
            if not re.match(r"^\d{4}-\d{2}-\d{2}([T ]\d{2}:\d{2}(:\d{2}(\.\d+)?)?)?$", s):
                raise ValueError
            t = np.datetime64(s.replace(" ", "T"), "ns")
        except ValueError:
            self.fail(
                f"{self.key(k)} = {v!r} is not a valid date; expected ISO 8601 such as "
                '"2019-01-01" or "2019-01-01T04:00:00" (UTC)'
            )
        return t

    def finish(self):
        unknown = [k for k in self.data if k not in self.used]
        if unknown:
            allowed = ", ".join(sorted(self.used))
            self.fail(
                f"unknown key {self.key(unknown[0])} = {self.data[unknown[0]]!r}; "
                f"allowed keys{' in [' + self.name + ']' if self.name else ''}: {allowed}"
            )


class _Values(dict):
    """The values of a section read so far (key -> value), for computed defaults and ranges."""

    def __init__(self, raw: dict, default_name: str = ""):
        super().__init__()
        self.raw = raw
        self.default_name = default_name

    def given(self, name: str) -> bool:
        """True when the case file has key ``name`` in this section."""
        return name in self.raw


def _resolve(x, values):
    return x(values) if callable(x) else x


def _read_key(sec: _Section, key: Key, values: _Values, base_dir: Optional[Path]) -> Any:
    """Validate one key of a section; return its value (its default if absent)."""
    k = key.name
    if key.only is not None:
        other, allowed = key.only
        if values[other] not in allowed:
            sec.used.add(k)
            if sec.has(k):
                which = " or ".join(repr(a) for a in allowed)
                sec.fail(
                    f"{sec.key(k)} = {sec.data[k]!r} is not used with {other} = {values[other]!r}; "
                    f"it applies to {other} = {which} only"
                )
            return key.dataclass_default
    if key.default is REQUIRED and not sec.has(k):
        when = f" ({key.only[0]} = {values[key.only[0]]!r})" if key.only is not None else ""
        sec.used.add(k)
        sec.fail(f"missing required key {sec.key(k)}{when}")
    default = None if key.default is REQUIRED else _resolve(key.default, values)
    t = key.type
    if t in ("float", "int"):
        return sec.number(
            k,
            default,
            lo=_resolve(key.lo, values),
            hi=_resolve(key.hi, values),
            lo_open=key.lo_open,
            hi_open=key.hi_open,
            unit=key.unit,
            integer=t == "int",
        )
    if t == "bool":
        return sec.boolean(k, default)
    if t == "str":
        return sec.string(k, default)
    if t == "choice":
        return sec.choice(k, key.choices, default)
    if t == "date":
        return sec.date(k)
    if t in ("file", "folder"):
        return _resolve_path(sec, k, base_dir, must_be_dir=t == "folder")
    if t == "profile":
        return _profile_label(sec, k, sec.raw(k, default))
    if t == "profiles":
        labels = sec.raw(k, list(default))
        if not isinstance(labels, list):
            sec.fail(
                f"{sec.key(k)} = {labels!r} has the wrong type ({type(labels).__name__}); "
                'expected a list of labels such as ["800/1100", "rock"]'
            )
        return tuple(_profile_label(sec, k, v, i) for i, v in enumerate(labels))
    if t == "grid":
        return _density_grid(sec, k, default)
    raise TypeError(f"schema key {key.dotted}: unknown type {t!r}")  # a schema bug, not user input


def _profile_label(sec: _Section, k: str, v: Any, index: Optional[int] = None) -> str:
    """A density profile label, checked by the profile parser the thermal model uses."""
    key = sec.key(k) + (f"[{index}]" if index is not None else "")
    if not isinstance(v, str):
        sec.fail(
            f"{key} = {v!r} has the wrong type ({type(v).__name__}); expected a profile label "
            'such as "1300/1800", "rock" or "hayne2017"'
        )
    try:
        profiles.parse_profile(v)
    except ProfileError as exc:
        sec.fail(f"{key} = {v!r} is not allowed: {exc}")
    return v.strip()


def _density_grid(sec: _Section, k: str, default: Optional[str]) -> Optional[str]:
    v = sec.string(k, default)
    if v is None:
        return None
    try:
        profiles.grid_densities(v)
    except ProfileError as exc:
        sec.fail(f"{sec.key(k)} = {v!r} is not allowed: {exc}")
    return v.strip()


def _resolve_path(sec: _Section, k: str, base_dir: Optional[Path], must_be_dir=False) -> Optional[Path]:
    v = sec.string(k, None)
    if v is None:
        return None
    p = Path(v).expanduser()
    if not p.is_absolute():
        if base_dir is None:
            sec.fail(f"{sec.key(k)} = {v!r} is relative, but the case has no file to be relative to")
        p = base_dir / p
    p = p.resolve()
    ok = p.is_dir() if must_be_dir else p.is_file()
    if not ok:
        what = "folder" if must_be_dir else "file"
        sec.fail(f"{sec.key(k)} = {v!r}: {what} not found ({p}); paths are relative to the case file")
    return p


# ---------------------------------------------------------------- checks across keys
def _check_sun(v: _Values, sec: _Section) -> None:
    if v["moon_frame"] == "de421" and v["moon_kernels"] is None:
        sec.fail(
            "sun.moon_frame = 'de421' needs sun.moon_kernels = folder with moon_080317.tf and "
            "moon_pa_de421_1900-2050.bpc (not shipped); or use moon_frame = 'iau2009'"
        )


def _check_period(v: _Values, sec: _Section) -> None:
    start, end = v["start"], v["end"]
    if end <= start:
        sec.fail(
            f"period.end = {np.datetime_as_string(end, unit='s')} must be after period.start = "
            f"{np.datetime_as_string(start, unit='s')}"
        )
    if v.given("spinup_years") and v.given("spinup_days"):
        sec.fail("give period.spinup_years or period.spinup_days, not both")
    if v["spinup_days"] is not None:
        v["spinup_years"] = v["spinup_days"] * 86400.0 / YEAR


#: Checks across the keys of one section, run after the section is read: f(values, section).
_SECTION_CHECKS: dict = {"sun": _check_sun, "period": _check_period}


def check_site_centre(
    where: str,
    source: str,
    site_lat_deg: Optional[float],
    site_lon_deg: Optional[float],
    lat_deg: float,
    lon_deg: float,
    fix: str,
) -> None:
    """Refuse a site (a DEM site's centre) that is not centred on the case's location.

    The site's frame (east/north/up at its centre) is the frame of the Sun vectors, computed at
    ``location``: a site made for another centre would be lit from the wrong directions.

    Parameters
    ----------
    where : str
        Prefix of the message (the case file, or the mesh file).
    source : str
        Prefix of the key names in the message (``"crater."`` gives ``crater.center_lat_deg``).
    site_lat_deg, site_lon_deg : float or None [deg]
        The site's centre (None: not given, nothing to check).
    lat_deg, lon_deg : float [deg]
        ``location.lat_deg``, ``location.lon_deg``.
    fix : str
        How to fix it, ending the message.

    Raises
    ------
    ConfigError
        One line naming both values; longitudes are compared modulo 360 deg, to 1e-9 deg.
    """
    for axis, v, loc in (("lat", site_lat_deg, lat_deg), ("lon", site_lon_deg, lon_deg)):
        if v is None:
            continue
        d = float(v) - float(loc)
        if axis == "lon":
            d = (d + 180.0) % 360.0 - 180.0
        if abs(d) > 1e-9:
            raise ConfigError(
                f"{where}: {source}center_{axis}_deg = {float(v):g} differs from location.{axis}_deg = "
                f"{float(loc):g}; the site's frame is the location's ({fix})"
            )


def _check_case(case: Case, where: str) -> None:
    """Checks across sections: a DEM site is centred on the location; the period covers a flux step and lies
    inside the ephemeris."""
    if case.crater.kind == "dem":
        check_site_centre(
            where,
            "crater.",
            case.crater.center_lat_deg,
            case.crater.center_lon_deg,
            case.location.lat_deg,
            case.location.lon_deg,
            "give one of them, or the same value",
        )
        if case.crater.outer_resolution_m is not None and case.crater.outer_radius_km is None:
            raise ConfigError(f"{where}: crater.outer_resolution_m needs crater.outer_radius_km")
        if case.crater.outer_radius_km is not None and case.crater.outer_radius_km <= case.crater.radius_km:
            raise ConfigError(
                f"{where}: crater.outer_radius_km = {case.crater.outer_radius_km:g} must exceed "
                f"crater.radius_km = {case.crater.radius_km:g}"
            )
    if case.period.duration_s < case.steps.flux_step_s:
        raise ConfigError(
            f"{where}: period ({case.period.duration_s:g} s) is shorter than one flux step "
            f"steps.flux_step_hours = {case.steps.flux_step_hours:g}"
        )
    lo, hi, what = choices.ephemeris_span(case.sun.moon_frame)
    allowed = f"allowed: {np.datetime_as_string(lo, unit='D')} to {np.datetime_as_string(hi, unit='D')} (UTC, {what})"
    for key, t in (("period.start", case.period.start), ("period.end", case.period.end)):
        if not lo <= t <= hi:
            raise EphemerisRangeError(
                f"{where}: {key} = {np.datetime_as_string(t, unit='s')} is outside the ephemeris; {allowed}"
            )
    first = case.period.spinup_start
    if first < lo:
        raise EphemerisRangeError(
            f"{where}: period.spinup_years = {case.period.spinup_years:g} starts the spin-up at "
            f"{np.datetime_as_string(first, unit='s')}, outside the ephemeris; {allowed}"
        )


# ---------------------------------------------------------------- the builder
def _read_section(
    raw: dict, name: str, where: str, base_dir: Optional[Path], default_name: str = "", required: bool = False
) -> _Values:
    sec = _Section(raw if name == "" else raw.get(name), name, where)
    if required and name not in raw:
        sec.fail(f"missing section [{name}]")
    if name == "":
        sec.used.update(s.name for s in SECTIONS)
    values = _Values(sec.data, default_name)
    for key in _keys(name):
        values[key.name] = _read_key(sec, key, values, base_dir)
    check = _SECTION_CHECKS.get(name)
    if check is not None:
        check(values, sec)
    sec.finish()
    return values


def _build_case(raw: dict, text: str, base_dir: Optional[Path], path: Optional[Path], default_name: str) -> Case:
    where = str(path) if path is not None else "<case>"
    top = _read_section(raw, "", where, base_dir, default_name=default_name)
    if not top["name"] or not top["name"].strip():
        raise ConfigError(f"{where}: name = {top['name']!r} must not be empty")
    sections = {}
    for spec in SECTIONS:
        values = _read_section(raw, spec.name, where, base_dir, required=spec.required)
        fields = {k.name: values[k.name] for k in _keys(spec.name) if k.field}
        sections[spec.name] = _SECTION_CLASSES[spec.name](**fields)
    case = Case(name=top["name"].strip(), description=top["description"], toml_text=text, path=path, **sections)
    _check_case(case, where)
    return case


# ---------------------------------------------------------------- the README table
def _md_number(x) -> str:
    if not isinstance(x, float):
        return f"{x:,}".replace(",", " ")
    s = re.sub(r"e([+-])0*(\d)", r"e\1\2", f"{x:g}")
    return "−" + s[1:] if s.startswith("-") else s


def _md_unit(unit: str) -> str:
    return unit.replace("m-2", "m⁻²").replace("m-3", "m⁻³")


def _md_default(key: Key) -> str:
    if key.default_doc is not None:
        return key.default_doc
    d = key.default
    if d is REQUIRED:
        return f"required for `{key.only[1][0]}`" if key.only is not None else "required"
    if d is None:
        return "none"
    if isinstance(d, bool):
        return "true" if d else "false"
    if isinstance(d, str):
        return f'`"{d}"`' if key.type in ("choice", "profile", "grid") else f'"{d}"'
    if isinstance(d, tuple):
        return "[]" if not d else "[" + ", ".join(f'"{x}"' for x in d) + "]"
    if isinstance(d, float):
        return repr(d)
    return _md_number(d)


def _md_allowed(key: Key) -> str:
    if key.allowed_doc is not None:
        return key.allowed_doc
    if key.type == "choice":
        return ", ".join(f'`"{c}"`' for c in key.choices)
    if key.type == "file":
        return "an existing file"
    if key.type == "folder":
        return "an existing folder"
    if key.type not in ("float", "int") or (key.lo is None and key.hi is None):
        return ""
    unit = f" {_md_unit(key.unit)}" if key.unit else ""
    lo, hi = _md_number(key.lo), _md_number(key.hi)
    if key.lo_open or key.hi_open:
        sym = {"albedo": "A", "emissivity": "ε", "diameter_km": "D", "flux_step_hours": "h"}.get(key.name, "x")
        return f"{lo} {'<' if key.lo_open else '≤'} {sym} {'<' if key.hi_open else '≤'} {hi}{unit}"
    return f"{lo} … {hi}{unit}"


_MD_TYPES = {
    "str": "string",
    "choice": "string",
    "float": "float",
    "int": "int",
    "bool": "bool",
    "date": "ISO date string or TOML date/datetime",
    "file": "string",
    "folder": "string",
    "profile": "string",
    "profiles": "list of strings",
    "grid": "string",
}


def _md_meaning(key: Key) -> str:
    doc = key.doc
    if key.only is not None and key.only[0] == "kind":
        doc += f" (kind {', '.join(f'`{v}`' for v in key.only[1])} only)"
    return doc


def schema_markdown() -> str:
    """The key tables of cases/README.md (Markdown), generated from :data:`SCHEMA`."""
    out = [
        'Units are in the key names. "required" keys have no default. Generated from',
        "`crater_thermal.config.SCHEMA` by `python -m crater_thermal.config --update cases/README.md`;",
        "edit the schema, not this table.",
    ]
    for name, title in [("", "top level")] + [
        (s.name, f"`[{s.name}]`" + (" (required section)" if s.required else "")) for s in SECTIONS
    ]:
        out += ["", f"### {title}", "| key | type | default | allowed | meaning |", "|---|---|---|---|---|"]
        for key in _keys(name):
            row = [f"`{key.name}`", _MD_TYPES[key.type], _md_default(key), _md_allowed(key), _md_meaning(key)]
            out.append("| " + " | ".join(row) + " |")
    return "\n".join(out) + "\n"


_MD_BEGIN = "<!-- schema table: begin (generated) -->\n"
_MD_END = "<!-- schema table: end -->\n"


def readme_with_schema(text: str) -> str:
    """``text`` (cases/README.md) with the part between the schema markers regenerated."""
    try:
        a = text.index(_MD_BEGIN) + len(_MD_BEGIN)
        b = text.index(_MD_END, a)
    except ValueError:
        raise ConfigError(f"no schema markers {_MD_BEGIN.strip()!r} ... {_MD_END.strip()!r} in the text") from None
    return text[:a] + schema_markdown() + text[b:]


# ---------------------------------------------------------------- public entry points
def loads_case(text: str, base_dir: Optional[Path] = None, name: str = "case", path: Optional[Path] = None) -> Case:
    """Parse and validate case TOML text.

    Parameters
    ----------
    text : str
        TOML text.
    base_dir : Path, optional
        Folder that relative paths (``crater.mesh``, ``sun.moon_kernels``) refer to.
    name : str
        Default case name when the text has no ``name`` key.
    path : Path, optional
        Case file (for messages and ``Case.path``).

    Raises
    ------
    ConfigError, EphemerisRangeError
    """
    where = str(path) if path is not None else "<case>"
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}") from None
    return _build_case(raw, text, base_dir=base_dir, path=path, default_name=name)


def load_case(path) -> Case:
    """Read and validate a case file.

    Parameters
    ----------
    path : str or Path
        TOML case file. Relative paths inside it are relative to its folder.

    Returns
    -------
    Case
        Frozen; ``Case.toml_text`` holds the file's text.

    Raises
    ------
    ConfigError
        Unreadable file, invalid TOML, unknown key, wrong type, value out of range,
        missing mesh file; the message names the key, the value and what is allowed.
    EphemerisRangeError
        ``period`` (including the spin-up window) outside DE421.
    """
    p = Path(path).expanduser()
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"case file {str(path)!r} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"case file {str(path)!r} cannot be read ({type(exc).__name__}: {exc})") from None
    p = p.resolve()
    return loads_case(text, base_dir=p.parent, name=p.stem, path=p)


# ---------------------------------------------------------------- TOML writer (our schema only)
def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (_dt.datetime, _dt.date)):
        return v.isoformat()
    if isinstance(v, np.datetime64):
        return '"' + np.datetime_as_string(v, unit="s") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"cannot write {v!r} ({type(v).__name__}) to TOML")


def dump_toml(raw: Mapping[str, Any]) -> str:
    """Write a case's raw mapping (top-level keys + one level of tables) as TOML."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in raw.items() if not isinstance(v, dict)]
    for k, v in raw.items():
        if isinstance(v, dict):
            lines.append("")
            lines.append(f"[{k}]")
            lines.extend(f"{kk} = {_toml_value(vv)}" for kk, vv in v.items())
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    """``python -m crater_thermal.config --markdown`` prints the README key tables;
    ``--update PATH`` rewrites them in PATH (cases/README.md) between the schema markers."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m crater_thermal.config", description=main.__doc__)
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--markdown", action="store_true", help="print the key tables (Markdown)")
    g.add_argument("--update", metavar="README", help="regenerate the key tables in this file")
    args = ap.parse_args(argv)
    if args.markdown:
        sys.stdout.write(schema_markdown())
        return 0
    p = Path(args.update)
    old = p.read_text(encoding="utf-8")
    new = readme_with_schema(old)
    if new != old:
        p.write_text(new, encoding="utf-8")
    print(f"{p}: {'updated' if new != old else 'already current'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
