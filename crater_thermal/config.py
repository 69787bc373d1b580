"""Case files: TOML in, frozen dataclasses out, validated at the edge.

A case file describes one simulation. Every key, its unit, default and allowed
range is listed below (and in ``cases/README.md``). Unknown sections or keys,
wrong types and out-of-range values raise :class:`~crater_thermal.errors.ConfigError`
with one line naming the key, the value and what is allowed; dates outside the
ephemeris raise :class:`~crater_thermal.errors.EphemerisRangeError` naming the key.

Schema (units in the key names; defaults in brackets; "-" = required)::

    name        str     [file stem]   case name (labels outputs)
    description str     [""]          free text

    [crater]
    kind        str     ["crater", or "mesh" if `mesh` is given]
                        "crater": idealized crater, thesis Table 7.1 (Pike 1977)
                        "flat":   horizontal flat surface, no crater (thesis Fig. 7.9)
                        "mesh":   a mesh file
    diameter_km float   -             rim diameter, 0 < D <= 15 km (kind "crater" only)
    facets      int     [502]         triangles, 20 <= n <= 1_000_000 (kind "crater" only)
    surround_km float   [0.0]         width of the flat plain around the rim, 0 <= w <= 100 km
                                      (kind "crater" only)
    mesh        str     -             path of a .ply/.obj/.stl mesh [m, x east, y north, z up],
                                      relative to the case file (kind "mesh" only; must exist)

    [location]
    lat_deg     float   -             planetocentric latitude, -90 <= lat <= 90 deg
    lon_deg     float   [0.0]         east longitude, -360 <= lon <= 360 deg

    [period]
    start       date    -             first recorded instant, ISO 8601 ("2019-01-01" or
                                      "2019-01-01T00:00:00", UTC; a TOML date also works)
    end         date    -             last recorded instant (> start)
    spinup      str     ["periodic"]  "periodic": converge to the periodic steady state of the
                                      forcing over the `spinup_years` before `start`;
                                      "fixed": the thesis procedure, simulate `spinup_years`
                                      before `start` once, from `initial_temperature_K` or
                                      (if absent) the equilibrium estimate
    spinup_years float  [1.0 periodic, 3.0 fixed]
                                      length of the spin-up window [yr of 365.25 d];
                                      periodic: 29.5/365.25 (about a synodic month) <= y <= 50;
                                      fixed: 0 <= y <= 300 (window limited by the ephemeris)
    spinup_days float   -             alternative to spinup_years [d] (give one of them)
    initial_temperature_K float [none] uniform start temperature, 1 <= T <= 1000 K
                                      (fixed: the start; periodic: the first guess)
    periodic_tol_K float [0.01]       periodic convergence tolerance, 1e-6 <= tol <= 10 K

    [steps]
    flux_step_hours   float [4.0]     flux (boundary condition) step, 0 < h <= 24 h (thesis 4 h)
    conduction_step_s float [solver default]
                                      largest conduction sub-step, 0 < dt <= flux step [s]

    [surface]
    albedo            float [0.12]    Bond albedo, 0 <= A < 1
    emissivity        float [0.98]    infrared emissivity, 0 < eps <= 1
    property_set      str   ["apollo"] "apollo" (thesis) | "hayne2017"
    geothermal_flux_W_m2 float [0.033] heat flux into the column bottom, 0 <= q <= 1 W m-2
    nominal_profile   str   ["1300/1800"] density profile of the coupled run: "TOP/BOTTOM"
                                      [kg m-3, 100..4000], "rock" or "hayne2017"

    [sun]
    limb_darkening    str   ["linear"] "linear" | "quadratic" | "neckel_labs" | "uniform"
    point_sun         bool  [false]   true: a point Sun instead of the extended disk
    n_rings           int   [illumination default] rings of the Sun-disk model, 1..100
    solar_constant_W_m2 float [1361.0] irradiance at 1 au, 1000 <= S <= 2000 W m-2
    moon_frame        str   ["iau2009"] Moon orientation: "iau2009" | "de421"
    moon_kernels      str   [none]    folder with moon_080317.tf and moon_pa_de421_1900-2050.bpc,
                                      relative to the case file (required for "de421")
    correction        str   ["apparent"] Sun direction: "apparent" | "light_time" | "geometric"

    [scattering]
    method            str   ["exact"] "exact" (radiosity solve) | "bounces" (thesis: 3)
    n_bounces         int   [3]       bounces for method "bounces", 1..100

    [replay]
    profiles          list of str [[]] profiles replayed on the saved nominal fluxes
                                      (labels as for nominal_profile)
    density_grid      str   [none]    "LO:HI:STEP" [kg m-3], 100 <= LO <= HI <= 4000, STEP > 0

    [output]
    checkpoint_interval_steps int [0] checkpoint every n flux steps (0: only after spin-up),
                                      0 <= n <= 10_000_000
    save_spinup_fluxes bool [true]    also store the spin-up window's fluxes (replays then start exactly as the run did)
    chunk_mb          float [256]     memory [MB] for the run's (time, facet) blocks (sunlight, temperatures, IR are
                                      kept and written in blocks of time samples), 0.01 <= chunk_mb <= 1e6

The dataclass fields carry the TOML key names (units in the names); SI
conveniences are properties (``Case.flux_step_s``, ``Period.spinup_s``, ...).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional, Tuple

import numpy as np

from crater_thermal.constants import (
    ALBEDO,
    EMISSIVITY,
    GEOTHERMAL_FLUX,
    SOLAR_CONSTANT,
    YEAR,
)
from crater_thermal.errors import ConfigError, EphemerisRangeError

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
    "load_case",
    "loads_case",
    "dump_toml",
    "CRATER_KINDS",
    "SPINUP_MODES",
    "PROPERTY_SETS",
    "LIMB_DARKENING_LAWS",
    "SCATTERING_METHODS",
]

CRATER_KINDS = ("crater", "flat", "mesh")
SPINUP_MODES = ("periodic", "fixed")
PROPERTY_SETS = ("apollo", "hayne2017")
LIMB_DARKENING_LAWS = ("linear", "quadratic", "neckel_labs", "uniform")
SCATTERING_METHODS = ("exact", "bounces")
MOON_FRAMES = ("iau2009", "de421")
SUN_CORRECTIONS = ("apparent", "light_time", "geometric")

_PROFILE_RE = re.compile(r"^\s*(\d+(?:\.\d*)?)\s*/\s*(\d+(?:\.\d*)?)\s*$")
_GRID_RE = re.compile(r"^\s*(\d+(?:\.\d*)?)\s*:\s*(\d+(?:\.\d*)?)\s*:\s*(\d+(?:\.\d*)?)\s*$")
_MIN_PERIODIC_DAYS = 29.5  # [d] shortest periodic spin-up window (about one synodic month)
_DENSITY_RANGE = (100.0, 4000.0)  # [kg m-3] sanity bounds for labels; thermal.py checks physics


# ---------------------------------------------------------------- dataclasses
@dataclass(frozen=True)
class Crater:
    """Terrain of the case.

    kind : "crater" | "flat" | "mesh"
    diameter_km : float or None [km]  rim diameter (kind "crater")
    facets : int or None  number of triangles (kind "crater")
    surround_km : float [km]  flat plain around the rim (kind "crater")
    mesh : Path or None  absolute path of the mesh file (kind "mesh")
    """

    kind: str = "crater"
    diameter_km: Optional[float] = None
    facets: Optional[int] = None
    surround_km: float = 0.0
    mesh: Optional[Path] = None

    @property
    def n_facets(self) -> Optional[int]:
        return self.facets

    @property
    def diameter_m(self) -> Optional[float]:
        """Rim diameter [m] or None."""
        return None if self.diameter_km is None else self.diameter_km * 1e3


@dataclass(frozen=True)
class Location:
    """Crater centre: planetocentric latitude and east longitude [deg]."""

    lat_deg: float
    lon_deg: float = 0.0


@dataclass(frozen=True)
class Period:
    """Recorded period and spin-up.

    start, end : numpy.datetime64[ns] (UTC)  first and last recorded instant
    spinup : "periodic" | "fixed"
    spinup_years : float [yr of 365.25 d]  spin-up window before ``start``
    initial_temperature_K : float or None [K]
    periodic_tol_K : float [K]
    """

    start: np.datetime64
    end: np.datetime64
    spinup: str = "periodic"
    spinup_years: float = 1.0
    initial_temperature_K: Optional[float] = None
    periodic_tol_K: float = 0.01

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


@dataclass(frozen=True)
class Steps:
    """Time steps: flux step [h] and optional largest conduction sub-step [s]."""

    flux_step_hours: float = 4.0
    conduction_step_s: Optional[float] = None

    @property
    def flux_step_s(self) -> float:
        """Flux step [s]."""
        return self.flux_step_hours * 3600.0


@dataclass(frozen=True)
class Surface:
    """Surface and subsurface properties (see PHYSICS.md)."""

    albedo: float = ALBEDO
    emissivity: float = EMISSIVITY
    property_set: str = "apollo"
    geothermal_flux_W_m2: float = GEOTHERMAL_FLUX
    nominal_profile: str = "1300/1800"

    @property
    def geothermal_flux(self) -> float:
        """Geothermal flux [W m-2] (same number; SI name)."""
        return self.geothermal_flux_W_m2


@dataclass(frozen=True)
class Sun:
    """Sun model and ephemeris options."""

    limb_darkening: str = "linear"
    point_sun: bool = False
    n_rings: Optional[int] = None
    solar_constant_W_m2: float = SOLAR_CONSTANT
    moon_frame: str = "iau2009"
    moon_kernels: Optional[Path] = None
    correction: str = "apparent"

    @property
    def solar_constant(self) -> float:
        """Irradiance at 1 au [W m-2]."""
        return self.solar_constant_W_m2


@dataclass(frozen=True)
class Scattering:
    """Scattered sunlight: exact radiosity or ``n_bounces`` bounces."""

    method: str = "exact"
    n_bounces: int = 3


@dataclass(frozen=True)
class Replay:
    """Profiles replayed on the saved nominal fluxes."""

    profiles: Tuple[str, ...] = ()
    density_grid: Optional[str] = None


@dataclass(frozen=True)
class Output:
    """Output options."""

    checkpoint_interval_steps: int = 0
    save_spinup_fluxes: bool = True
    chunk_mb: float = 256.0


@dataclass(frozen=True)
class Case:
    """A validated case. Build with :func:`load_case` / :func:`loads_case`.

    Attributes
    ----------
    name : str
    crater, location, period, steps, surface, sun, scattering, replay, output : sections
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
    replay: Replay = Replay()
    output: Output = Output()
    toml_text: str = ""
    path: Optional[Path] = None
    description: str = ""

    # conveniences (interface names)
    @property
    def flux_step_s(self) -> float:
        return self.steps.flux_step_s

    @property
    def conduction_step_s(self) -> Optional[float]:
        return self.steps.conduction_step_s

    @property
    def nominal_profile(self) -> str:
        return self.surface.nominal_profile

    @property
    def profiles(self) -> Tuple[str, ...]:
        return self.replay.profiles

    @property
    def density_grid(self) -> Optional[str]:
        return self.replay.density_grid

    @property
    def checkpoint_interval_steps(self) -> int:
        return self.output.checkpoint_interval_steps

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
            self.name, ", ".join(f"{k} = {v!r}" for k, v in overrides.items()))
        text = header + dump_toml(raw)
        base = self.path.parent if self.path is not None else None
        return _build_case(raw, text, base_dir=base, path=self.path, default_name=self.name)


def _strip_derived(raw: dict) -> dict:
    return {k: (dict(v) if isinstance(v, dict) else v) for k, v in raw.items()}


# ---------------------------------------------------------------- validation helpers
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

    def number(self, k, default=None, lo=None, hi=None, lo_open=False, hi_open=False, unit="",
               required=False, integer=False):
        v = self.raw(k, default, required)
        if k not in self.data:
            return default
        kind = "an integer" if integer else "a number"
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)):
            self.fail(f"{self.key(k)} = {v!r} has the wrong type ({type(v).__name__}); expected {kind}, "
                      f"allowed: {_fmt_range(lo, hi, lo_open, hi_open, unit)}")
        if not math.isfinite(v):
            self.fail(f"{self.key(k)} = {v!r} is not finite; allowed: {_fmt_range(lo, hi, lo_open, hi_open, unit)}")
        bad = ((lo is not None and (v < lo or (lo_open and v == lo)))
               or (hi is not None and (v > hi or (hi_open and v == hi))))
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
            self.fail(f"{self.key(k)} = {v!r} has the wrong type ({type(v).__name__}); "
                      "expected an ISO 8601 date such as \"2019-01-01\" or \"2019-01-01T04:00:00\"")
        s = v.strip()
        if s.endswith(("Z", "z")):
            s = s[:-1]
        try:
            if not re.match(r"^\d{4}-\d{2}-\d{2}([T ]\d{2}:\d{2}(:\d{2}(\.\d+)?)?)?$", s):
                raise ValueError
            t = np.datetime64(s.replace(" ", "T"), "ns")
        except ValueError:
            self.fail(f"{self.key(k)} = {v!r} is not a valid date; expected ISO 8601 such as "
                      "\"2019-01-01\" or \"2019-01-01T04:00:00\" (UTC)")
        return t

    def finish(self):
        unknown = [k for k in self.data if k not in self.used]
        if unknown:
            allowed = ", ".join(sorted(self.used))
            self.fail(f"unknown key {self.key(unknown[0])} = {self.data[unknown[0]]!r}; "
                      f"allowed keys{' in [' + self.name + ']' if self.name else ''}: {allowed}")


def _profile_label(sec: _Section, k: str, v: Any, index: Optional[int] = None) -> str:
    key = sec.key(k) + (f"[{index}]" if index is not None else "")
    if not isinstance(v, str):
        sec.fail(f"{key} = {v!r} has the wrong type ({type(v).__name__}); expected a profile label "
                 "such as \"1300/1800\", \"rock\" or \"hayne2017\"")
    label = v.strip()
    if label in ("rock", "hayne2017"):
        return label
    m = _PROFILE_RE.match(label)
    if not m:
        sec.fail(f"{key} = {v!r} is not a profile label; allowed: \"TOP/BOTTOM\" densities in kg m-3 "
                 "(e.g. \"1300/1800\"), \"rock\" or \"hayne2017\"")
    lo, hi = _DENSITY_RANGE
    for rho in (float(m.group(1)), float(m.group(2))):
        if not lo <= rho <= hi:
            sec.fail(f"{key} = {v!r} has a density {rho:g} out of range; allowed: "
                     f"{lo:g} <= rho <= {hi:g} [kg m-3]")
    return label


def _density_grid(sec: _Section, k: str) -> Optional[str]:
    v = sec.string(k, None)
    if v is None:
        return None
    m = _GRID_RE.match(v)
    if not m:
        sec.fail(f"{sec.key(k)} = {v!r} is not a density grid; allowed: \"LO:HI:STEP\" in kg m-3, "
                 "e.g. \"800:2000:100\"")
    lo, hi, step = (float(g) for g in m.groups())
    rlo, rhi = _DENSITY_RANGE
    if not (rlo <= lo <= hi <= rhi) or step <= 0:
        sec.fail(f"{sec.key(k)} = {v!r} out of range; allowed: {rlo:g} <= LO <= HI <= {rhi:g} "
                 "and STEP > 0 [kg m-3]")
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


_SECTIONS = ("crater", "location", "period", "steps", "surface", "sun", "scattering", "replay", "output")


def _build_case(raw: dict, text: str, base_dir: Optional[Path], path: Optional[Path],
                default_name: str) -> Case:
    where = str(path) if path is not None else "<case>"
    top = _Section(raw, "", where)
    for s in _SECTIONS:
        top.used.add(s)
    name = top.string("name", default_name)
    if not name or not name.strip():
        top.fail(f"name = {name!r} must not be empty")
    description = top.string("description", "")
    top.finish()

    # [crater]
    sec = _Section(raw.get("crater"), "crater", where)
    if "crater" not in raw:
        sec.fail("missing section [crater]")
    default_kind = "mesh" if sec.has("mesh") else "crater"
    kind = sec.choice("kind", CRATER_KINDS, default_kind)
    crater_keys = ("diameter_km", "facets", "surround_km")
    if kind == "crater":
        if sec.has("mesh"):
            sec.fail("crater.mesh is given with kind = 'crater'; use kind = 'mesh' (or drop the mesh key)")
        crater = Crater(
            kind="crater",
            diameter_km=sec.number("diameter_km", lo=0.0, hi=15.0, lo_open=True, unit="km", required=True),
            facets=sec.number("facets", 502, lo=20, hi=1_000_000, integer=True),
            surround_km=sec.number("surround_km", 0.0, lo=0.0, hi=100.0, unit="km"),
        )
    else:
        for k in crater_keys:
            if sec.has(k):
                sec.fail(f"crater.{k} = {sec.data[k]!r} is not used with kind = {kind!r}; "
                         f"it applies to kind = 'crater' only")
        if kind == "flat":
            if sec.has("mesh"):
                sec.fail("crater.mesh is given with kind = 'flat'; use kind = 'mesh'")
            crater = Crater(kind="flat")
        else:
            if not sec.has("mesh"):
                sec.fail("missing required key crater.mesh (kind = 'mesh')")
            crater = Crater(kind="mesh", mesh=_resolve_path(sec, "mesh", base_dir))
    sec.finish()

    # [location]
    sec = _Section(raw.get("location"), "location", where)
    if "location" not in raw:
        sec.fail("missing section [location]")
    location = Location(
        lat_deg=sec.number("lat_deg", lo=-90.0, hi=90.0, unit="deg", required=True),
        lon_deg=sec.number("lon_deg", 0.0, lo=-360.0, hi=360.0, unit="deg"),
    )
    sec.finish()

    # [sun] first: the Moon frame decides the usable date range
    sec = _Section(raw.get("sun"), "sun", where)
    moon_frame = sec.choice("moon_frame", MOON_FRAMES, "iau2009")
    moon_kernels = _resolve_path(sec, "moon_kernels", base_dir, must_be_dir=True)
    if moon_frame == "de421" and moon_kernels is None:
        sec.fail("sun.moon_frame = 'de421' needs sun.moon_kernels = folder with moon_080317.tf and "
                 "moon_pa_de421_1900-2050.bpc (not shipped); or use moon_frame = 'iau2009'")
    sun = Sun(
        limb_darkening=sec.choice("limb_darkening", LIMB_DARKENING_LAWS, "linear"),
        point_sun=sec.boolean("point_sun", False),
        n_rings=sec.number("n_rings", None, lo=1, hi=100, integer=True),
        solar_constant_W_m2=sec.number("solar_constant_W_m2", SOLAR_CONSTANT, lo=1000.0, hi=2000.0,
                                       unit="W m-2"),
        moon_frame=moon_frame,
        moon_kernels=moon_kernels,
        correction=sec.choice("correction", SUN_CORRECTIONS, "apparent"),
    )
    sec.finish()

    # [period]
    sec = _Section(raw.get("period"), "period", where)
    if "period" not in raw:
        sec.fail("missing section [period]")
    start, end = sec.date("start"), sec.date("end")
    if end <= start:
        sec.fail(f"period.end = {np.datetime_as_string(end, unit='s')} must be after period.start = "
                 f"{np.datetime_as_string(start, unit='s')}")
    spinup = sec.choice("spinup", SPINUP_MODES, "periodic")
    # a periodic state needs at least one lunar day of forcing (29.5 d)
    min_years = _MIN_PERIODIC_DAYS * 86400.0 / YEAR if spinup == "periodic" else 0.0
    max_years = 50.0 if spinup == "periodic" else 300.0
    if sec.has("spinup_years") and sec.has("spinup_days"):
        sec.fail("give period.spinup_years or period.spinup_days, not both")
    if sec.has("spinup_days"):
        days = sec.number("spinup_days", lo=min_years * YEAR / 86400.0, hi=max_years * 365.25, unit="d")
        spinup_years = days * 86400.0 / YEAR
        sec.used.add("spinup_years")
    else:
        sec.used.add("spinup_days")
        spinup_years = sec.number("spinup_years", 1.0 if spinup == "periodic" else 3.0,
                                  lo=min_years, hi=max_years, unit="yr")
    period = Period(
        start=start,
        end=end,
        spinup=spinup,
        spinup_years=spinup_years,
        initial_temperature_K=sec.number("initial_temperature_K", None, lo=1.0, hi=1000.0, unit="K"),
        periodic_tol_K=sec.number("periodic_tol_K", 0.01, lo=1e-6, hi=10.0, unit="K"),
    )
    sec.finish()
    _check_period_range(period, moon_frame, where)

    # [steps]
    sec = _Section(raw.get("steps"), "steps", where)
    flux_h = sec.number("flux_step_hours", 4.0, lo=0.0, hi=24.0, lo_open=True, unit="h")
    steps = Steps(
        flux_step_hours=flux_h,
        conduction_step_s=sec.number("conduction_step_s", None, lo=0.0, hi=flux_h * 3600.0, lo_open=True,
                                     unit="s"),
    )
    sec.finish()
    if period.duration_s < steps.flux_step_s:
        raise ConfigError(f"{where}: period ({period.duration_s:g} s) is shorter than one flux step "
                          f"steps.flux_step_hours = {flux_h:g}")

    # [surface]
    sec = _Section(raw.get("surface"), "surface", where)
    surface = Surface(
        albedo=sec.number("albedo", ALBEDO, lo=0.0, hi=1.0, hi_open=True),
        emissivity=sec.number("emissivity", EMISSIVITY, lo=0.0, hi=1.0, lo_open=True),
        property_set=sec.choice("property_set", PROPERTY_SETS, "apollo"),
        geothermal_flux_W_m2=sec.number("geothermal_flux_W_m2", GEOTHERMAL_FLUX, lo=0.0, hi=1.0, unit="W m-2"),
        nominal_profile=_profile_label(sec, "nominal_profile", sec.raw("nominal_profile", "1300/1800")),
    )
    sec.finish()

    # [scattering]
    sec = _Section(raw.get("scattering"), "scattering", where)
    scattering = Scattering(
        method=sec.choice("method", SCATTERING_METHODS, "exact"),
        n_bounces=sec.number("n_bounces", 3, lo=1, hi=100, integer=True),
    )
    sec.finish()

    # [replay]
    sec = _Section(raw.get("replay"), "replay", where)
    labels = sec.raw("profiles", [])
    if not isinstance(labels, list):
        sec.fail(f"replay.profiles = {labels!r} has the wrong type ({type(labels).__name__}); "
                 "expected a list of labels such as [\"800/1100\", \"rock\"]")
    replay = Replay(
        profiles=tuple(_profile_label(sec, "profiles", v, i) for i, v in enumerate(labels)),
        density_grid=_density_grid(sec, "density_grid"),
    )
    sec.finish()

    # [output]
    sec = _Section(raw.get("output"), "output", where)
    output = Output(
        checkpoint_interval_steps=sec.number("checkpoint_interval_steps", 0, lo=0, hi=10_000_000, integer=True),
        save_spinup_fluxes=sec.boolean("save_spinup_fluxes", True),
        chunk_mb=sec.number("chunk_mb", 256.0, lo=0.01, hi=1e6),
    )
    sec.finish()

    return Case(name=name.strip(), crater=crater, location=location, period=period, steps=steps,
                surface=surface, sun=sun, scattering=scattering, replay=replay, output=output,
                toml_text=text, path=path, description=description)


def _check_period_range(period: Period, moon_frame: str, where: str) -> None:
    from crater_thermal import ephemeris

    lo, hi, what = ephemeris.ephemeris_range(moon_frame)
    allowed = (f"allowed: {np.datetime_as_string(lo, unit='D')} to {np.datetime_as_string(hi, unit='D')} "
               f"(UTC, {what})")
    for key, t in (("period.start", period.start), ("period.end", period.end)):
        if not lo <= t <= hi:
            raise EphemerisRangeError(f"{where}: {key} = {np.datetime_as_string(t, unit='s')} is outside the "
                                      f"ephemeris; {allowed}")
    first = period.spinup_start
    if first < lo:
        raise EphemerisRangeError(
            f"{where}: period.spinup_years = {period.spinup_years:g} starts the spin-up at "
            f"{np.datetime_as_string(first, unit='s')}, outside the ephemeris; {allowed}")


# ---------------------------------------------------------------- public entry points
def loads_case(text: str, base_dir: Optional[Path] = None, name: str = "case",
               path: Optional[Path] = None) -> Case:
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
