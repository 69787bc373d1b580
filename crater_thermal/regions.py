"""Night and day masks and named facet regions of a run (no xarray: the datasets' mapping interface).

Conventions (thesis sections 7.2-7.3; issue 10)
-----------------------------------------------
* **Night** is a property of the (time, facet) sample (:func:`night_day_masks`, default
  ``definition="dark"``): a sample is night for a facet when that facet has had no sunlight at all, direct
  or scattered (``solar_incident <= DARK_THRESHOLD_W_M2``), for at least :data:`MIN_DARK_HOURS` (24 h), so
  the hours after the facet's own sunset, when it is still cooling, are excluded, and so are the weeks in
  which a permanently shadowed floor is warmed by the light its sunlit walls scatter. Its **day** is the
  samples in which it receives sunlight (direct or scattered) and that are not night. A facet whose dark
  night covers less than :data:`NIGHT_FALLBACK_FRACTION` of the record (near the pole a floor may never go a
  day without scattered light) falls back to that fraction of its samples of least sunlight among those
  without direct sunlight for ``min_dark_hours`` (:func:`dark_night_mask`), and is flagged.
  ``definition="facet"`` counts only direct sunlight (``solar_direct == 0`` for ``min_dark_hours``): a
  never-lit facet (a PSR floor) then has night all the time (after the first 24 h of the record) and no
  day. The thesis's definition, night when the Sun's centre is below the crater centre's horizon
  (``sun_direction[:, 2] < 0``, the same for all facets), is ``definition="centre"`` (:func:`night_mask`),
  kept for comparisons with the thesis.
* **Regions** are named facet masks (:func:`region_masks`, :func:`crater_region_masks`); they may overlap.
  ``floor``; ``lower_wall`` / ``upper_wall``: the wall below / above half of its *vertical* extent;
  ``top_wall_ring``: the wall facets touching the rim crest (part of the upper wall); ``rim``: the outer
  flank; ``surround``. Walls, top ring and rim are split into four sectors by the azimuth the facet's slope
  *faces* (its normal's horizontal part), +-45 deg around ``pole_facing``, ``equator_facing``,
  ``east_facing``, ``west_facing``: ``upper_wall_equator_facing`` is the wall on the pole side of the
  crater, facing the equator and the Sun. At |lat| >= :data:`POLAR_LIMIT_DEG` the sectors are named by the
  Sun's mean azimuth over the run (``sun_facing``, ``antisun_facing``, ``sun_left_facing``,
  ``sun_right_facing``). The illumination classes ``never_lit`` / ``rarely_lit`` (< 10% of samples) /
  ``often_lit`` work on any mesh, as do :func:`slope_classes` and :func:`facing_classes` (by normal
  azimuth), which replace the crater regions on a mesh without crater meta (a DEM).
  The thesis-style partition (inner/outer halves of the wall in radius, the pole side / equator side of
  the axis) is :func:`classify_regions` / :data:`REGIONS`, kept for comparisons.
"""

from __future__ import annotations

from typing import Dict, Mapping, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from crater_thermal import io
from crater_thermal.errors import ConfigError, FluxFileError

#: Thesis-style region partition (classify_regions: wall halves in radius, pole side / equator side of the axis).
#: The report uses region_masks (named by what the sets hold); these are kept for thesis comparisons.
REGIONS: Tuple[str, ...] = (
    "floor",
    "lower_wall_poleward",
    "lower_wall_equatorward",
    "upper_wall_poleward",
    "upper_wall_equatorward",
    "rim_poleward",
    "rim_equatorward",
    "surround",
)


def night_mask(sun_direction) -> np.ndarray:
    """Night at the crater centre: the Sun's centre below the local horizon.

    Parameters
    ----------
    sun_direction : (nt, 3) float [unit] or a dataset with ``sun_direction``
        Unit vectors toward the Sun in the crater frame (x east, y north, z up).

    Returns
    -------
    (nt,) bool
        True where ``z < 0``; day is the complement.
    """
    s = sun_direction["sun_direction"].values if hasattr(sun_direction, "attrs") else sun_direction
    s = np.asarray(s, dtype=float)
    if s.ndim != 2 or s.shape[1] != 3:
        raise FluxFileError(f"sun_direction must have shape (time, 3), got {s.shape}")
    return s[:, 2] < 0.0


def day_mask(sun_direction) -> np.ndarray:
    """(nt,) bool: the Sun's centre on or above the horizon at the crater centre (not night)."""
    return ~night_mask(sun_direction)


def shadow_mask(solar_direct) -> np.ndarray:
    """(nt, nf) bool: facet receives no direct sunlight (``solar_direct == 0``) [W m-2 input]."""
    e = solar_direct["solar_direct"].values if hasattr(solar_direct, "attrs") else solar_direct
    return np.asarray(e, dtype=float) <= 0.0


def pole_direction(lat_deg: float) -> np.ndarray:
    """(2,) horizontal unit vector toward the nearer pole in the crater frame: -y south, +y north.

    At exactly 0 deg the equator has no poleward side; the southern convention (-y) is used.
    """
    if not -90.0 <= float(lat_deg) <= 90.0:
        raise ConfigError(f"lat_deg={lat_deg} out of range [-90, 90]")
    return np.array([0.0, 1.0]) if lat_deg > 0 else np.array([0.0, -1.0])


def rim_width_m(meta: Mapping) -> float:
    """Outer-flank width [m]: ``meta["rim_width_m"]`` or Pike (1977) 0.257 D^1.011 km, D = rim diameter [km]."""
    if meta.get("rim_width_m") is not None:
        return float(meta["rim_width_m"])
    d_km = 2.0 * float(meta["rim_radius_m"]) / 1000.0
    return 0.257 * d_km**1.011 * 1000.0


def classify_regions(centroids, meta: Mapping, lat_deg: float, wall_split: float = 0.5) -> np.ndarray:
    """Region label of every facet (see the module docstring and :data:`REGIONS`).

    Parameters
    ----------
    centroids : (nf, 3) float [m]
        Facet centroids in the crater frame.
    meta : mapping
        Mesh meta with ``floor_radius_m`` and ``rim_radius_m`` [m] (``rim_width_m`` optional).
        A ``"bowl"`` (spherical cap) without ``floor_radius_m`` has no floor; ``rim_radius_m``
        defaults to ``diameter_m / 2``; a ``"flat"`` mesh without a rim is all ``surround``.
    lat_deg : float [deg]
        Crater latitude (sets the pole side).
    wall_split : float [-]
        Fraction of the wall's radial extent (from the floor edge) that is "lower wall"; (0, 1).

    Returns
    -------
    (nf,) str array of labels from :data:`REGIONS`.
    """
    meta = dict(meta)
    kind = meta.get("kind")
    if meta.get("rim_radius_m") is None and meta.get("diameter_m") is not None:
        meta["rim_radius_m"] = 0.5 * float(meta["diameter_m"])
    if meta.get("floor_radius_m") is None and kind == "bowl":
        meta["floor_radius_m"] = 0.0  # a spherical cap has no flat floor
    c = np.asarray(centroids, dtype=float)
    if meta.get("rim_radius_m") is None and kind == "flat":
        return np.full(len(c), "surround")
    for key in ("floor_radius_m", "rim_radius_m"):
        if meta.get(key) is None:
            raise FluxFileError(f"mesh_meta lacks {key!r}, needed for region classes (kind={kind})")
    if not 0.0 < wall_split < 1.0:
        raise ConfigError(f"wall_split={wall_split} out of range (0, 1)")
    rf, rr = float(meta["floor_radius_m"]), float(meta["rim_radius_m"])
    if not 0.0 <= rf < rr:
        raise FluxFileError(f"mesh_meta floor_radius_m={rf} must be in [0, rim_radius_m={rr})")
    r = np.hypot(c[:, 0], c[:, 1])
    r_mid = rf + wall_split * (rr - rf)
    r_out = rr + rim_width_m(meta)
    base = np.full(len(c), "surround", dtype=object)
    base[r <= r_out] = "rim"
    base[r <= rr] = "upper_wall"
    base[r <= r_mid] = "lower_wall"
    if rf > 0:  # a bowl (rf = 0) has no floor, even at r = 0
        base[r <= rf] = "floor"
    pole = pole_direction(lat_deg)
    poleward = c[:, :2] @ pole > 0.0
    sided = np.isin(base, ("lower_wall", "upper_wall", "rim"))
    labels = base.copy()
    labels[sided & poleward] = [f"{b}_poleward" for b in base[sided & poleward]]
    labels[sided & ~poleward] = [f"{b}_equatorward" for b in base[sided & ~poleward]]
    return labels.astype(str)


def regions_of(ds, wall_split: float = 0.5) -> np.ndarray:
    """:func:`classify_regions` for a run/replay dataset (centroids, mesh_meta, lat_deg)."""
    return classify_regions(ds["centroid"].values, io.mesh_meta(ds), io.latitude_deg(ds), wall_split=wall_split)


# ------------------------------------------------------------------------ per-facet night, regions
#
# Issue 10 (items 4 and 5). A facet's night is a property of the (time, facet) sample; regions are
# named boolean masks over facets (they may overlap: the top wall ring is part of the upper wall,
# the illumination classes cut across everything).

#: Night definitions: "dark" (default; no sunlight at all, direct or scattered, on that facet for
#: ``min_dark_hours``, with the least-lit fallback: :func:`dark_night_mask`), "facet" (no direct sunlight on
#: that facet for ``min_dark_hours``; a PSR floor is then "night" all year), "centre" (the thesis: the Sun's
#: centre below the crater centre's horizon, the same for every facet) and "facet_and_centre" (both "facet"
#: and "centre": a PSR floor's night is then the centre's).
NIGHT_DEFINITIONS: Tuple[str, ...] = ("dark", "facet", "centre", "facet_and_centre")
#: The default night definition.
DEFAULT_NIGHT = "dark"
#: Default darkness a facet needs before its samples count as night [h]: one Earth day excludes the
#: first hours after sunset, when the surface is still cooling from the day (thesis Fig. 7.5).
MIN_DARK_HOURS = 24.0
#: Direct flux [W m-2] at or below which a facet counts as unlit. The ray tracer returns exactly 0 for
#: a facet that sees no part of the solar disk (the flux is a sum of positive patch weights times
#: max(0, cos i) over visible patches), so no tolerance is needed: any sliver of disk counts as lit.
LIT_THRESHOLD_W_M2 = 0.0
#: Total sunlight (direct + scattered, ``solar_incident``) [W m-2] at or below which a facet counts as dark
#: ("dark" night). Absorbed, (1 - 0.12) x 1e-3 = 8.8e-4 W m-2 is 2.7% of the 0.033 W m-2 geothermal flux
#: and 0.6% of what a surface at 40 K emits (0.98 sigma 40^4 = 0.142 W m-2); in radiative equilibrium it
#: warms such a surface by 8.8e-4 / (4 x 0.142 / 40 K) = 0.06 K, against night-time loose - nominal
#: contrasts of 1-3 K. Scattered light while any wall in view is sunlit is 1e-1 to 1e1 W m-2, so the
#: threshold separates the two. The radiosity solve gives exactly 0 when nothing is lit; the threshold
#: also absorbs round-off.
DARK_THRESHOLD_W_M2 = 1e-3
#: Fraction of the record [-]: a facet whose "dark" night holds fewer samples than this falls back to this
#: fraction of its samples of least sunlight (among those with no direct sunlight for ``min_dark_hours``).
NIGHT_FALLBACK_FRACTION = 0.1
#: |lat| at and above which the pole direction is undefined in practice and sectors are named by the
#: Sun's mean azimuth over the run [deg].
POLAR_LIMIT_DEG = 89.5
#: Illumination classes: "never_lit" (lit fraction 0), "rarely_lit" (0 < f < RARELY_LIT_MAX_FRACTION),
#: "often_lit" (f >= RARELY_LIT_MAX_FRACTION); f = fraction of the run's samples with direct sunlight.
RARELY_LIT_MAX_FRACTION = 0.1
ILLUMINATION_CLASSES: Tuple[str, ...] = ("never_lit", "rarely_lit", "often_lit")
#: Slope class edges [deg] (facet normal from vertical); classes are named ``slope_<lo>_<hi>_deg``.
SLOPE_EDGES_DEG: Tuple[float, ...] = (0.0, 5.0, 15.0, 25.0, 90.0)
#: Facets sloping less than this [deg] have no facing direction ("level" in :func:`facing_classes`).
LEVEL_MAX_SLOPE_DEG = 2.0
#: Sector names (pole-facing first, equator-facing, east, west) and their names at |lat| >= POLAR_LIMIT_DEG
#: (matched one to one: away from the Sun's mean azimuth, toward it, then the two sides).
SECTORS: Tuple[str, ...] = ("pole_facing", "equator_facing", "east_facing", "west_facing")
POLAR_SECTORS_SOUTH: Tuple[str, ...] = ("antisun_facing", "sun_facing", "sun_right_facing", "sun_left_facing")
POLAR_SECTORS_NORTH: Tuple[str, ...] = ("antisun_facing", "sun_facing", "sun_left_facing", "sun_right_facing")
#: Crater parts that are split into sectors, in plotting order.
SECTORED_PARTS: Tuple[str, ...] = ("lower_wall", "upper_wall", "top_wall_ring", "rim")


def _values(x, name: str) -> np.ndarray:
    return np.asarray(x[name].values if hasattr(x, "attrs") else x, dtype=float)


def seconds_of(time) -> np.ndarray:
    """Times [s] since the first one, from datetime64 or numbers of seconds."""
    t = np.asarray(time)
    if np.issubdtype(t.dtype, np.datetime64):
        return (t.astype("datetime64[ns]") - t.astype("datetime64[ns]")[0]).astype(np.int64) / 1e9
    return t.astype(float) - float(t.ravel()[0]) if t.size else t.astype(float)


def lit_mask(solar_direct, threshold_W_m2: float = LIT_THRESHOLD_W_M2) -> np.ndarray:
    """(nt, nf) bool: facet directly lit, ``solar_direct > threshold_W_m2`` [W m-2]."""
    return _values(solar_direct, "solar_direct") > float(threshold_W_m2)


def facet_night_mask(
    solar_direct, time, min_dark_hours: float = MIN_DARK_HOURS, threshold_W_m2: float = LIT_THRESHOLD_W_M2
) -> np.ndarray:
    """Per-facet night: the facet has had no direct sunlight for at least ``min_dark_hours``.

    Parameters
    ----------
    solar_direct : (nt, nf) float [W m-2]
        Direct solar irradiance per sample and facet (a run's ``solar_direct``).
    time : (nt,) datetime64 or float [s]
        Sample times, increasing.
    min_dark_hours : float [h]
        Darkness required, >= 0. 0 makes every unlit sample night.
    threshold_W_m2 : float [W m-2]
        Lit means ``solar_direct > threshold`` (default 0: see :data:`LIT_THRESHOLD_W_M2`).

    Returns
    -------
    (nt, nf) bool
        Sample k is night for facet j when the facet is unlit at k and ``t_k - t_dark >= min_dark``,
        where ``t_dark`` is the first unlit sample after the last lit one. Fluxes are linear between
        samples, so a facet lit at sample m still receives light until sample m + 1: darkness is counted
        from there. Before the record the facet's history is unknown and taken as lit, so the first
        ``min_dark_hours`` of a record are never night (conservative; 6 of 2190 samples of a year at 4 h).
    """
    return _dark_for(lit_mask(solar_direct, threshold_W_m2), time, min_dark_hours, "solar_direct")


def _dark_for(lit, time, min_dark_hours: float, name: str) -> np.ndarray:
    """(nt, nf) bool: unlit and unlit since at least ``min_dark_hours`` [h] (see :func:`facet_night_mask`)."""
    if not (np.isfinite(min_dark_hours) and min_dark_hours >= 0):
        raise ConfigError(f"min_dark_hours={min_dark_hours} out of range [0, inf)")
    if lit.ndim != 2:
        raise FluxFileError(f"{name} must have shape (time, facet), got {lit.shape}")
    t = seconds_of(time)
    if t.shape != (lit.shape[0],):
        raise FluxFileError(f"time has {t.size} samples, {name} {lit.shape[0]}")
    nt = lit.shape[0]
    idx = np.arange(nt)[:, None]
    # index of the first dark sample of the current dark spell: (last lit sample) + 1, or 0 at the start
    last_lit = np.maximum.accumulate(np.where(lit, idx, -1), axis=0)
    dark_since = t[np.clip(last_lit + 1, 0, nt - 1)]
    dark_for = t[:, None] - dark_since  # a spell without a lit sample before it counts from t[0]
    return ~lit & (dark_for >= min_dark_hours * 3600.0 - 1e-6)


def least_lit_mask(solar_incident, candidates, fraction: float = NIGHT_FALLBACK_FRACTION) -> np.ndarray:
    """(nt, nf) bool: per facet, the ``fraction`` of the record with the least sunlight among ``candidates``.

    Parameters
    ----------
    solar_incident : (nt, nf) float [W m-2]
        Total sunlight (direct + scattered) per sample and facet.
    candidates : (nt, nf) bool
        Samples that may be chosen (e.g. no direct sunlight for ``min_dark_hours``).
    fraction : float [-]
        In (0, 1]: ``ceil(fraction * nt)`` samples per facet, or all its candidates if it has fewer.

    Returns
    -------
    (nt, nf) bool
        Deterministic: candidates sorted by flux, ties by time (earliest first); every chosen sample has
        no more sunlight than any candidate left out. A facet without candidates gets none.
    """
    if not (np.isfinite(fraction) and 0.0 < fraction <= 1.0):
        raise ConfigError(f"fallback fraction={fraction} out of range (0, 1]")
    e = np.asarray(solar_incident, float)
    c = np.asarray(candidates, bool)
    if e.ndim != 2 or c.shape != e.shape:
        raise FluxFileError(f"solar_incident {e.shape} and candidates {c.shape} must both be (time, facet)")
    nt = e.shape[0]
    k = int(np.ceil(fraction * nt - 1e-9))
    order = np.argsort(np.where(c, e, np.inf), axis=0, kind="stable")  # non-candidates last
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.arange(nt)[:, None].repeat(e.shape[1], axis=1), axis=0)
    return c & (rank < k)


class NightSelection(NamedTuple):
    """Night and day samples of a run, and how they were chosen (:func:`night_selection`).

    night, day : (nt, nf) bool; fallback : (nf,) bool, facets whose night is the least-lit fallback;
    definition : str; min_dark_hours [h]; threshold_W_m2 [W m-2] (on ``solar_incident`` for "dark", on
    ``solar_direct`` otherwise); fallback_fraction [-] (None unless "dark").
    """

    night: np.ndarray
    day: np.ndarray
    fallback: np.ndarray
    definition: str
    min_dark_hours: float
    threshold_W_m2: Optional[float]
    fallback_fraction: Optional[float]


def dark_night_mask(
    solar_incident,
    solar_direct,
    time,
    min_dark_hours: float = MIN_DARK_HOURS,
    threshold_W_m2: float = DARK_THRESHOLD_W_M2,
    fallback_fraction: float = NIGHT_FALLBACK_FRACTION,
) -> Tuple[np.ndarray, np.ndarray]:
    """Per-facet night without any sunlight ("dark"), with the least-lit fallback.

    Parameters
    ----------
    solar_incident : (nt, nf) float [W m-2]
        Direct + scattered sunlight per sample and facet (a run's ``solar_incident``).
    solar_direct : (nt, nf) float [W m-2]
        Direct sunlight (a run's ``solar_direct``), for the fallback's candidates.
    time : (nt,) datetime64 or float [s]
    min_dark_hours : float [h]
        Darkness required (counted as in :func:`facet_night_mask`).
    threshold_W_m2 : float [W m-2]
        Dark means ``solar_incident <= threshold_W_m2`` (:data:`DARK_THRESHOLD_W_M2`) and no direct
        sunlight at all (``solar_direct == 0``: a sliver of the disk counts as lit, as in
        :func:`facet_night_mask`), so the dark night is part of the "facet" night.
    fallback_fraction : float [-]
        A facet whose dark night has fewer than ``ceil(fallback_fraction * nt)`` samples uses instead the
        ``fallback_fraction`` of the record with the least ``solar_incident`` among its samples without
        direct sunlight for ``min_dark_hours`` (:func:`least_lit_mask`): never a directly lit sample, nor
        one in the ``min_dark_hours`` after direct light. A facet directly lit in every such window has no
        night. With one albedo for scattered light the least incident sunlight is the least absorbed.

    Returns
    -------
    night : (nt, nf) bool
    fallback : (nf,) bool
        Facets whose night is the fallback.
    """
    if not (np.isfinite(threshold_W_m2) and threshold_W_m2 >= 0):
        raise ConfigError(f"dark threshold_W_m2={threshold_W_m2} out of range [0, inf)")
    e = np.asarray(solar_incident, float)
    direct = lit_mask(solar_direct)
    if direct.shape != e.shape:
        raise FluxFileError(f"solar_direct {direct.shape} and solar_incident {e.shape} differ in shape")
    night = _dark_for((e > float(threshold_W_m2)) | direct, time, min_dark_hours, "solar_incident")
    candidates = _dark_for(direct, time, min_dark_hours, "solar_direct")  # facet_night_mask
    least = least_lit_mask(e, candidates, fallback_fraction)  # also checks fallback_fraction
    fallback = night.sum(axis=0) < int(np.ceil(fallback_fraction * e.shape[0] - 1e-9))
    night[:, fallback] = least[:, fallback]
    return night, fallback


def night_selection(
    run,
    definition: str = DEFAULT_NIGHT,
    min_dark_hours: float = MIN_DARK_HOURS,
    threshold_W_m2: Optional[float] = None,
    fallback_fraction: float = NIGHT_FALLBACK_FRACTION,
) -> NightSelection:
    """Night and day masks of shape (nt, nf) for a run dataset, with the facets that fell back.

    ``definition="dark"`` (default): night = :func:`dark_night_mask` (no sunlight, direct or scattered,
    ``solar_incident <= threshold_W_m2``, default :data:`DARK_THRESHOLD_W_M2`, for ``min_dark_hours`` [h];
    the least-lit ``fallback_fraction`` of the record where a facet has fewer dark samples than that); day =
    the facet receives sunlight (``solar_incident > threshold_W_m2``) and the sample is not night.
    ``"facet"``: night = :func:`facet_night_mask` (direct sunlight only, threshold default
    :data:`LIT_THRESHOLD_W_M2`), day = the facet is directly lit (the samples in between, the first
    ``min_dark_hours`` after the facet's sunset, are in neither); a facet that is never lit has no day.
    ``"centre"``: the thesis definition, the Sun's centre below / above the crater centre's horizon
    (:func:`night_mask`), the same for every facet. ``"facet_and_centre"``: night by both "facet" and
    "centre" (a never-lit floor is then night only while the Sun is below the centre's horizon); day as
    "facet". Only "dark" falls back.
    """
    if definition not in NIGHT_DEFINITIONS:
        raise ConfigError(f"night definition {definition!r} not one of {', '.join(NIGHT_DEFINITIONS)}")
    nf = run["surface_temperature"].shape[1]
    none = np.zeros(nf, bool)
    if definition == "centre":
        n = night_mask(run)
        night, day = np.repeat(n[:, None], nf, axis=1), np.repeat(~n[:, None], nf, axis=1)
        return NightSelection(night, day, none, definition, float(min_dark_hours), None, None)
    if not io.has_variable(run, "solar_direct"):
        raise FluxFileError("run dataset has no solar_direct: per-facet night needs it (use definition='centre')")
    e = run["solar_direct"].values
    if definition == "dark":
        if not io.has_variable(run, "solar_incident"):
            raise FluxFileError("run dataset has no solar_incident: the 'dark' night needs it")
        thr = DARK_THRESHOLD_W_M2 if threshold_W_m2 is None else float(threshold_W_m2)
        ei = np.asarray(run["solar_incident"].values, float)
        night, fallback = dark_night_mask(ei, e, run["time"].values, min_dark_hours, thr, fallback_fraction)
        day = (ei > thr) & ~night
        return NightSelection(night, day, fallback, definition, float(min_dark_hours), thr, float(fallback_fraction))
    thr = LIT_THRESHOLD_W_M2 if threshold_W_m2 is None else float(threshold_W_m2)
    night = facet_night_mask(e, run["time"].values, min_dark_hours, thr)
    if definition == "facet_and_centre":
        night &= night_mask(run)[:, None]
    return NightSelection(night, lit_mask(e, thr), none, definition, float(min_dark_hours), thr, None)


def night_day_masks(
    run, definition: str = DEFAULT_NIGHT, min_dark_hours: float = MIN_DARK_HOURS, threshold_W_m2: Optional[float] = None
) -> Tuple[np.ndarray, np.ndarray]:
    """(night, day) masks of shape (nt, nf) for a run dataset (:func:`night_selection`, which also says
    which facets fell back). ``threshold_W_m2`` [W m-2]: default :data:`DARK_THRESHOLD_W_M2` on
    ``solar_incident`` for "dark", :data:`LIT_THRESHOLD_W_M2` on ``solar_direct`` otherwise."""
    sel = night_selection(run, definition, min_dark_hours, threshold_W_m2)
    return sel.night, sel.day


def lit_fraction(solar_direct, threshold_W_m2: float = LIT_THRESHOLD_W_M2) -> np.ndarray:
    """(nf,) [-]: fraction of samples in which each facet is directly lit."""
    return lit_mask(solar_direct, threshold_W_m2).mean(axis=0)


def illumination_classes(
    solar_direct, threshold_W_m2: float = LIT_THRESHOLD_W_M2, rarely_max_fraction: float = RARELY_LIT_MAX_FRACTION
) -> Dict[str, np.ndarray]:
    """Facets by how often they are directly lit over the run; works on any mesh.

    Returns
    -------
    dict ``never_lit`` (no sample with direct sunlight), ``rarely_lit`` (lit in fewer than
    ``rarely_max_fraction`` of the samples), ``often_lit`` (the rest) -> (nf,) bool.
    """
    if not 0.0 < rarely_max_fraction <= 1.0:
        raise ConfigError(f"rarely_max_fraction={rarely_max_fraction} out of range (0, 1]")
    f = lit_fraction(solar_direct, threshold_W_m2)
    return {
        "never_lit": f == 0.0,
        "rarely_lit": (f > 0.0) & (f < rarely_max_fraction),
        "often_lit": f >= rarely_max_fraction,
    }


def slope_deg(normals) -> np.ndarray:
    """(nf,) [deg]: angle of each facet's (unit, upward) normal from the local vertical +z."""
    n = np.asarray(normals, float)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(n[:, 2], -1.0, 1.0)))


def slope_classes(normals, edges_deg: Sequence[float] = SLOPE_EDGES_DEG) -> Dict[str, np.ndarray]:
    """Facets by slope: ``slope_<lo>_<hi>_deg`` for lo <= slope < hi (the last bin includes hi) [deg]."""
    e = [float(x) for x in edges_deg]
    if len(e) < 2 or any(b <= a for a, b in zip(e, e[1:])) or e[0] < 0 or e[-1] > 180:
        raise ConfigError(f"slope edges {edges_deg} must increase within [0, 180] deg")
    s = slope_deg(normals)
    out = {}
    for k, (a, b) in enumerate(zip(e, e[1:])):
        hi = (s <= b) if k == len(e) - 2 else (s < b)
        out[f"slope_{a:g}_{b:g}_deg"] = (s >= a) & hi
    return out


def mean_sun_azimuth(sun_direction) -> Tuple[np.ndarray, float]:
    """Horizontal unit vector of the Sun's mean azimuth over a run, and its weight [-].

    Each sample's horizontal Sun direction is weighted by the sine of the elevation of the disk's upper
    limb when that is above the horizon (the flux a level surface would get, up to the disk's extent),
    so the mean points to where the sunlight came from. The second value is the length of the weighted
    mean of unit vectors (1: always the same azimuth, 0: no preferred azimuth, e.g. a full circle).
    """
    s = _values(sun_direction, "sun_direction")
    if s.ndim != 2 or s.shape[1] != 3:
        raise FluxFileError(f"sun_direction must have shape (time, 3), got {s.shape}")
    w = np.clip(s[:, 2] + SUN_ANGULAR_RADIUS_RAD, 0.0, None)
    h = s[:, :2]
    norm = np.linalg.norm(h, axis=1)
    ok = (norm > 0) & (w > 0)
    if not ok.any():
        return np.array([0.0, 1.0]), 0.0
    u = h[ok] / norm[ok, None]
    m = (w[ok, None] * u).sum(axis=0) / w[ok].sum()
    r = float(np.linalg.norm(m))
    return (m / r if r > 0 else np.array([0.0, 1.0])), r


#: Angular radius of the Sun at 1 au [rad] (used only to weight the mean Sun azimuth).
SUN_ANGULAR_RADIUS_RAD = 4.65e-3


def sector_axes(lat_deg: float, sun_direction=None, polar_limit_deg: float = POLAR_LIMIT_DEG) -> Dict[str, np.ndarray]:
    """The four facing directions, name -> (2,) horizontal unit vector in the crater frame (x east, y north).

    For |lat| < ``polar_limit_deg``: ``pole_facing`` (toward the nearer pole: -y south, +y north),
    ``equator_facing``, ``east_facing`` (+x), ``west_facing`` (-x). At the pole every horizontal
    direction points away from the pole, so the sectors are named by the Sun's mean azimuth over the run
    (:func:`mean_sun_azimuth`, needs ``sun_direction``): ``sun_facing``, ``antisun_facing`` and
    ``sun_left_facing`` / ``sun_right_facing`` (left/right of an observer at the crater centre who faces
    the mean Sun). The order matches :data:`SECTORS` one to one (antisun = pole-like, sun = equator-like).
    """
    if not -90.0 <= float(lat_deg) <= 90.0:
        raise ConfigError(f"lat_deg={lat_deg} out of range [-90, 90]")
    if abs(float(lat_deg)) < polar_limit_deg:
        p = pole_direction(lat_deg)
        return dict(zip(SECTORS, (p, -p, np.array([1.0, 0.0]), np.array([-1.0, 0.0]))))
    if sun_direction is None:
        raise ConfigError(
            f"at |lat| >= {polar_limit_deg} deg sectors are named by the Sun's mean azimuth: sun_direction is needed"
        )
    s, _ = mean_sun_azimuth(sun_direction)
    right = np.array([s[1], -s[0]])  # s turned 90 deg clockwise seen from above (+z)
    names = POLAR_SECTORS_SOUTH if lat_deg < 0 else POLAR_SECTORS_NORTH
    by_name = {"antisun_facing": -s, "sun_facing": s, "sun_right_facing": right, "sun_left_facing": -right}
    return {n: by_name[n] for n in names}


def _sector_index(directions, axes: Sequence[np.ndarray]) -> np.ndarray:
    """(n,) index of the axis nearest in azimuth to each horizontal direction (ties: first axis)."""
    d = np.asarray(directions, float)[:, :2]
    return np.argmax(d @ np.asarray(axes, float).T, axis=1)


def facing_classes(
    normals, lat_deg: float, sun_direction=None, level_max_slope_deg: float = LEVEL_MAX_SLOPE_DEG
) -> Dict[str, np.ndarray]:
    """Facets by the azimuth their slope faces (the normal's horizontal part); works on any mesh.

    Returns
    -------
    dict: the four sectors of :func:`sector_axes` (each the facets whose normal azimuth lies within
    +-45 deg of the sector's direction) and ``level`` (slope < ``level_max_slope_deg`` [deg], no facing).
    """
    axes = sector_axes(lat_deg, sun_direction)
    n = np.asarray(normals, float)
    level = slope_deg(n) < level_max_slope_deg
    k = _sector_index(n, list(axes.values()))
    out = {name: (k == i) & ~level for i, name in enumerate(axes)}
    out["level"] = level
    return out


def crater_region_masks(
    centroids, normals, vertices, faces, meta: Mapping, lat_deg: float, sun_direction=None, wall_split: float = 0.5
) -> Dict[str, np.ndarray]:
    """Crater regions as named facet masks (issue 10: the names say what the sets hold).

    Parts (by the centroid's distance r from the axis and height z; meta as in :func:`classify_regions`):

    * ``floor``: r <= floor radius.
    * ``lower_wall`` / ``upper_wall``: wall facets (floor radius < r <= rim radius) whose centroid lies
      below / at or above ``wall_split`` of the wall's vertical extent, h = (z - z_floor) / (z_rim - z_floor)
      with z_floor = ``meta["floor_z_m"]`` (else rim height - depth, else the lowest centroid) and z_rim the
      crest height (``meta["rim_height_m"]``, else the highest vertex at r <= rim radius).
    * ``top_wall_ring``: wall facets with a vertex on the rim crest (|r_vertex - rim radius| <= 1 mm +
      1e-6 rim radius): the wall's top ring of facets, a subset of ``upper_wall``.
    * ``rim``: the outer flank, rim radius < r <= rim radius + rim width; ``surround`` beyond.

    Every part but the floor and the surround is split into four 90-degree sectors by the azimuth its
    slope *faces* (the facet normal's horizontal direction, :func:`sector_axes`), named
    ``<part>_<sector>``, e.g. ``upper_wall_equator_facing`` (on the pole side of the crater, facing the
    equator and the Sun) or ``rim_pole_facing`` (the outer flank on the pole side). A wall or rim facet
    steeper than 0.5 deg always has a facing; flatter ones (none on the idealized craters) take the
    facing of their position (wall: toward the axis; rim: away from it).

    Returns
    -------
    dict name -> (nf,) bool, in plotting order: floor, the sectored parts, surround.
    """
    meta = dict(meta)
    c = np.asarray(centroids, float)
    n = np.asarray(normals, float)
    v = np.asarray(vertices, float)
    f = np.asarray(faces, int)
    kind = meta.get("kind")
    nf = len(c)
    if meta.get("rim_radius_m") is None and meta.get("diameter_m") is not None:
        meta["rim_radius_m"] = 0.5 * float(meta["diameter_m"])
    if meta.get("floor_radius_m") is None and kind == "bowl":
        meta["floor_radius_m"] = 0.0
    if meta.get("rim_radius_m") is None and kind == "flat":
        return {"surround": np.ones(nf, bool)}
    for key in ("floor_radius_m", "rim_radius_m"):
        if meta.get(key) is None:
            raise FluxFileError(
                f"mesh_meta lacks {key!r}, needed for crater regions (kind={kind}); "
                "use illumination_classes / slope_classes / facing_classes on other meshes"
            )
    if not 0.0 < wall_split < 1.0:
        raise ConfigError(f"wall_split={wall_split} out of range (0, 1)")
    rf, rr = float(meta["floor_radius_m"]), float(meta["rim_radius_m"])
    if not 0.0 <= rf < rr:
        raise FluxFileError(f"mesh_meta floor_radius_m={rf} must be in [0, rim_radius_m={rr})")
    r = np.hypot(c[:, 0], c[:, 1])
    r_out = rr + rim_width_m(meta)
    rv = np.hypot(v[:, 0], v[:, 1])
    if meta.get("floor_z_m") is not None:
        z_floor = float(meta["floor_z_m"])
    elif meta.get("rim_height_m") is not None and meta.get("depth_m") is not None:
        z_floor = float(meta["rim_height_m"]) - float(meta["depth_m"])
    else:
        z_floor = float(c[:, 2].min())
    inside = rv <= rr * (1 + 1e-9) + 1e-6
    z_rim = float(meta["rim_height_m"]) if meta.get("rim_height_m") is not None else float(v[inside, 2].max())
    if not z_rim > z_floor:
        raise FluxFileError(f"crater rim height {z_rim} m is not above the floor {z_floor} m")
    wall = (r > rf) & (r <= rr) if rf > 0 else (r <= rr)
    floor = (r <= rf) if rf > 0 else np.zeros(nf, bool)
    h = (c[:, 2] - z_floor) / (z_rim - z_floor)
    on_crest = np.abs(rv - rr) <= 1e-3 + 1e-6 * rr
    parts = {
        "lower_wall": wall & (h < wall_split),
        "upper_wall": wall & (h >= wall_split),
        "top_wall_ring": wall & on_crest[f].any(axis=1),
        "rim": (r > rr) & (r <= r_out),
    }
    axes = sector_axes(lat_deg, sun_direction)
    facing = n[:, :2].copy()
    flat = slope_deg(n) < 0.5
    radial = c[:, :2] / np.maximum(r, 1e-12)[:, None]
    facing[flat & wall] = -radial[flat & wall]
    facing[flat & ~wall] = radial[flat & ~wall]
    k = _sector_index(facing, list(axes.values()))
    out = {"floor": floor}
    for part in SECTORED_PARTS:
        for i, name in enumerate(axes):
            out[f"{part}_{name}"] = parts[part] & (k == i)
    out["surround"] = r > r_out
    return out


def region_names(lat_deg: float, polar_limit_deg: float = POLAR_LIMIT_DEG) -> Tuple[str, ...]:
    """Crater region names (plotting order) at a latitude, then the illumination classes."""
    south = float(lat_deg) < 0
    sectors = (
        SECTORS if abs(float(lat_deg)) < polar_limit_deg else (POLAR_SECTORS_SOUTH if south else POLAR_SECTORS_NORTH)
    )
    return (
        ("floor",) + tuple(f"{p}_{s}" for p in SECTORED_PARTS for s in sectors) + ("surround",) + ILLUMINATION_CLASSES
    )


def region_masks(
    run,
    wall_split: float = 0.5,
    threshold_W_m2: float = LIT_THRESHOLD_W_M2,
    rarely_max_fraction: float = RARELY_LIT_MAX_FRACTION,
) -> Dict[str, np.ndarray]:
    """Named facet masks of a run dataset: crater regions (when the mesh meta describes a crater or bowl),
    then the illumination classes (when the run has ``solar_direct``). On a mesh without crater meta
    (a DEM, ``kind="file"``), the slope and facing classes replace the crater regions.
    """
    meta = io.mesh_meta(run)
    lat = io.latitude_deg(run)
    sun = run["sun_direction"].values if io.has_variable(run, "sun_direction") else None
    normals = run["normal"].values if io.has_variable(run, "normal") else None
    c = run["centroid"].values
    if normals is None:
        normals = mesh_normals(run["mesh_vertices"].values, run["mesh_faces"].values)
    out: Dict[str, np.ndarray] = {}
    crater = meta.get("kind") in ("crater", "bowl") or meta.get("rim_radius_m") is not None
    if crater:
        out.update(
            crater_region_masks(
                c, normals, run["mesh_vertices"].values, run["mesh_faces"].values, meta, lat, sun, wall_split
            )
        )
    elif meta.get("kind") == "flat":
        out["surround"] = np.ones(len(c), bool)
    else:
        out.update(slope_classes(normals))
        out.update(facing_classes(normals, lat, sun))
    if io.has_variable(run, "solar_direct"):
        out.update(illumination_classes(run["solar_direct"].values, threshold_W_m2, rarely_max_fraction))
    if "inner" in run:  # a DEM site's outer ring only casts shadows and radiates: not analysed
        inner = np.asarray(run["inner"].values).astype(bool)
        out = {k: np.asarray(v, bool) & inner for k, v in out.items()}
    return out


def mesh_normals(vertices, faces) -> np.ndarray:
    """(nf, 3) unit facet normals (right-hand rule on the face's vertex order) from vertices [m] and faces."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces, int)
    cr = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return cr / np.linalg.norm(cr, axis=1, keepdims=True)
