"""Analysis of run/replay datasets: differences between profiles, their statistics, local time.

This module receives datasets (xarray ``Dataset`` objects from :mod:`crater_thermal.io`) and uses
only their mapping interface (``ds["name"].values``, ``ds.attrs``): it does not import xarray.
Every numerical function also works on plain numpy arrays. Night/day masks and the named facet
regions the statistics pool over are in :mod:`crater_thermal.regions`; the checks of the datasets
in :mod:`crater_thermal.io`; profile labels in :mod:`crater_thermal.profiles`.

Conventions (thesis sections 7.2-7.3)
-------------------------------------
* **Differences** are replayed profile minus nominal profile, per time and facet [K].
  Statistics pool all (time, facet) samples of a region (unweighted by area, as in the thesis).

Instrument model and detection statistics: :mod:`crater_thermal.instrument`.
"""

from __future__ import annotations

from typing import Dict, Iterator, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from crater_thermal import io, profiles, regions
from crater_thermal.constants import LOOSE_PROFILE
from crater_thermal.errors import ConfigError, FluxFileError

#: Default |dT| threshold [K] for the "fraction of time above" statistic: the 0.94 K natural scatter.
NATURAL_SCATTER_K = 0.94


def masked_statistics(
    dT, sample_mask, facet_masks: Mapping[str, np.ndarray], threshold_K: float = NATURAL_SCATTER_K
) -> Dict[str, dict]:
    """Pooled statistics per named facet set over the (time, facet) samples selected by ``sample_mask``.

    Parameters
    ----------
    dT : (nt, nf) float [K]
    sample_mask : (nt, nf) bool (e.g. per-facet night) or (nt,) bool (the same times for every facet)
    facet_masks : dict name -> (nf,) bool (e.g. :func:`region_masks`)

    Returns
    -------
    dict name -> :func:`pooled_stats` dict (None values when a set has no samples).
    """
    dT = np.asarray(dT, dtype=float)
    sm = np.asarray(sample_mask, bool)
    if sm.ndim == 1:
        sm = np.repeat(sm[:, None], dT.shape[1], axis=1)
    if sm.shape != dT.shape:
        raise FluxFileError(f"sample mask shape {sm.shape} does not match the field's {dT.shape}")
    return {
        name: pooled_stats(dT[:, m][sm[:, m]], threshold_K)
        for name, m in ((k, np.asarray(v, bool)) for k, v in facet_masks.items())
    }


def masked_median(values, sample_mask, facet_mask) -> Optional[float]:
    """Median of ``values`` (nt, nf) over the selected samples of the selected facets, None if empty."""
    v = np.asarray(values, float)
    sm = np.asarray(sample_mask, bool)
    if sm.ndim == 1:
        sm = np.repeat(sm[:, None], v.shape[1], axis=1)
    fm = np.asarray(facet_mask, bool)
    sel = v[:, fm][sm[:, fm]]
    return float(np.median(sel)) if sel.size else None


def facet_median_map(dT, sample_mask) -> np.ndarray:
    """(nf,) [K] per-facet median over that facet's selected samples (NaN where it has none)."""
    dT = np.asarray(dT, dtype=float)
    sm = np.asarray(sample_mask, bool)
    if sm.ndim == 1:
        return night_median_map(dT, sm)
    out = np.full(dT.shape[1], np.nan)
    for j in np.flatnonzero(sm.any(axis=0)):
        out[j] = np.median(dT[sm[:, j], j])
    return out


# ----------------------------------------------------------------------------------- differences


def nominal_label(ds, replay=None) -> str:
    """Label of the nominal profile: ``attrs["nominal_profile"]`` or the thesis default "1300/1800"."""
    lab = (replay.attrs.get("nominal_profile") if replay is not None else None) or ds.attrs.get("nominal_profile")
    return str(lab) if lab else profiles.NOMINAL_LABEL


def profile_labels(replay) -> List[str]:
    """Profile labels of a replay dataset, as str."""
    return [str(p) for p in np.asarray(replay["profile"].values)]


def find_profile(replay, top: float, bottom: float) -> Optional[str]:
    """Label of the replayed profile with these densities [kg m-3] (by rho_top/rho_bottom or label)."""
    labels = profile_labels(replay)
    if io.has_variable(replay, "rho_top") and io.has_variable(replay, "rho_bottom"):
        rt, rb = np.asarray(replay["rho_top"].values, float), np.asarray(replay["rho_bottom"].values, float)
        for lab, a, b in zip(labels, rt, rb):
            if "rock" not in lab.lower() and abs(a - top) < 0.5 and abs(b - bottom) < 0.5:
                return lab
    want = profiles.profile_label((top, bottom))
    return want if want in labels else None


def nominal_temperature(run, replay=None) -> np.ndarray:
    """(nt, nf) [K] nominal surface temperature: the replayed nominal profile if present, else the run's.

    The replayed nominal uses the same conduction start as the other replayed profiles, so using it
    keeps start-up differences out of the differences.
    """
    if replay is not None:
        lab = nominal_label(run, replay)
        labels = profile_labels(replay)
        if lab not in labels:
            top_bottom = profiles.parse_two_layer(lab)
            lab = find_profile(replay, *top_bottom) if top_bottom else None
        if lab is not None:
            return np.asarray(replay["surface_temperature"][labels.index(lab)].values, dtype=float)
    return np.asarray(run["surface_temperature"].values, dtype=float)


def profile_temperature(replay, label: str) -> np.ndarray:
    """(nt, nf) [K] surface temperature of one replayed profile (reads only that slice)."""
    labels = profile_labels(replay)
    if label not in labels:
        raise ConfigError(f"profile={label!r} not in the replay; allowed: {', '.join(labels)}")
    return np.asarray(replay["surface_temperature"][labels.index(label)].values, dtype=float)


def iter_profile_differences(run, replay, nominal_T=None) -> Iterator[Tuple[str, np.ndarray]]:
    """Yield ``(label, dT)`` for every replayed profile except the nominal, one at a time.

    dT : (nt, nf) float [K] = profile minus nominal. Only one profile is in memory at a time
    (a thesis density grid has ~90 profiles of (8766, 502) samples).
    """
    io.check_pair(run, replay)
    nom = nominal_temperature(run, replay) if nominal_T is None else nominal_T
    nom_lab = nominal_label(run, replay)
    for lab in profile_labels(replay):
        if lab != nom_lab:
            yield lab, profile_temperature(replay, lab) - nom


def profile_differences(run, replay) -> Dict[str, np.ndarray]:
    """Replayed profile minus nominal, per time and facet.

    Returns
    -------
    dict label -> (nt, nf) float [K], for every replayed profile except the nominal one.
    (Holds them all in memory; :func:`iter_profile_differences` does not.)
    """
    return dict(iter_profile_differences(run, replay))


def loose_label(replay, nominal: str) -> Optional[str]:
    """The thesis's "loose" profile (800/1100) if replayed, else the first non-nominal regolith profile."""
    lab = find_profile(replay, *LOOSE_PROFILE)
    if lab is not None:
        return lab
    for lab in profile_labels(replay):
        if lab != nominal and not profiles.is_rock(lab):
            return lab
    return None


def rock_label(replay) -> Optional[str]:
    """The first rock profile label, if any."""
    for lab in profile_labels(replay):
        if profiles.is_rock(lab):
            return lab
    return None


# ------------------------------------------------------------------------------------ statistics


def pooled_stats(values, threshold_K: float = NATURAL_SCATTER_K) -> Dict[str, Optional[float]]:
    """Median, quartiles and fraction with |value| > threshold of a pooled sample.

    Returns a dict with ``median_K, q1_K, q3_K, frac_above_threshold, n`` (None when empty).
    """
    v = np.asarray(values, dtype=float).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return dict(median_K=None, q1_K=None, q3_K=None, frac_above_threshold=None, n=0)
    q1, med, q3 = np.percentile(v, [25, 50, 75])
    return dict(
        median_K=float(med),
        q1_K=float(q1),
        q3_K=float(q3),
        frac_above_threshold=float(np.mean(np.abs(v) > threshold_K)),
        n=int(v.size),
    )


def region_statistics(
    dT, time_mask, regions, threshold_K: float = NATURAL_SCATTER_K, region_names: Sequence[str] = regions.REGIONS
) -> Dict[str, dict]:
    """Per-region pooled statistics of a (nt, nf) field over the selected times.

    Parameters
    ----------
    dT : (nt, nf) float [K]
    time_mask : (nt,) bool
        Times to use (e.g. :func:`night_mask`).
    regions : (nf,) str
        From :func:`classify_regions`.
    threshold_K : float [K]
        For ``frac_above_threshold`` (fraction of samples with |dT| > threshold).

    Returns
    -------
    dict region -> :func:`pooled_stats` dict, for every name in ``region_names`` (empty regions give None values).
    """
    dT = np.asarray(dT, dtype=float)
    tm = np.asarray(time_mask, dtype=bool)
    regions = np.asarray(regions)
    return {reg: pooled_stats(dT[tm][:, regions == reg], threshold_K) for reg in region_names}


def night_median_map(dT, night) -> np.ndarray:
    """(nf,) [K] per-facet median over night-time samples (NaN if there is no night)."""
    dT = np.asarray(dT, dtype=float)
    night = np.asarray(night, bool)
    if not night.any():
        return np.full(dT.shape[1], np.nan)
    return np.median(dT[night], axis=0)


def density_grid(replay, values: Mapping[str, float], nominal: Optional[str] = None):
    """Arrange one value per two-layer profile on the top x bottom density grid.

    Parameters
    ----------
    replay : dataset with ``profile`` (and ``rho_top``, ``rho_bottom`` [kg m-3]; else parsed from labels)
    values : dict label -> float
        E.g. night-time median differences [K]; rock profiles are ignored.
    nominal : str, optional
        Nominal label; its cell is 0 when absent from ``values``.

    Returns
    -------
    tops, bottoms : (ntop,), (nbottom,) float [kg m-3], sorted unique densities
    grid : (ntop, nbottom) float, NaN where no value (e.g. top > bottom, not replayed)
    """
    labels = profile_labels(replay)
    if io.has_variable(replay, "rho_top") and io.has_variable(replay, "rho_bottom"):
        rt = np.asarray(replay["rho_top"].values, float)
        rb = np.asarray(replay["rho_bottom"].values, float)
    else:
        pairs = [profiles.parse_two_layer(lab) or (np.nan, np.nan) for lab in labels]
        rt, rb = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    keep = [
        i for i, lab in enumerate(labels) if not profiles.is_rock(lab) and np.isfinite(rt[i]) and np.isfinite(rb[i])
    ]
    tops = np.unique(rt[keep])
    bottoms = np.unique(rb[keep])
    grid = np.full((tops.size, bottoms.size), np.nan)
    for i in keep:
        lab = labels[i]
        if lab in values and values[lab] is not None:
            val = float(values[lab])
        elif lab == nominal:
            val = 0.0
        else:
            continue
        grid[np.searchsorted(tops, rt[i]), np.searchsorted(bottoms, rb[i])] = val
    return tops, bottoms, grid


def density_grid_medians(replay, diffs: Mapping[str, np.ndarray], night, facet_mask, nominal: Optional[str] = None):
    """Night-time median difference over the two-layer density grid (thesis Fig. 7.7a).

    Parameters
    ----------
    replay : dataset with ``profile``, ``rho_top``, ``rho_bottom``
    diffs : dict label -> (nt, nf) [K]  (from :func:`profile_differences`)
    night : (nt,) bool
    facet_mask : (nf,) bool
        Facets pooled (e.g. the floor).
    nominal : str, optional
        Nominal label (its cell is 0 K).

    Returns
    -------
    tops, bottoms, grid : as :func:`density_grid`, grid [K].
    """
    night = np.asarray(night, bool)
    fm = np.asarray(facet_mask, bool)
    med = {}
    if night.any() and fm.any():
        med = {
            lab: float(np.median(np.asarray(d)[night][:, fm])) for lab, d in diffs.items() if not profiles.is_rock(lab)
        }
    return density_grid(replay, med, nominal)


def representative_facets(run, regions) -> Dict[str, int]:
    """Facets for time-series figures (thesis Figs. 7.4-7.6).

    ``regions``: (nf,) labels (:func:`classify_regions`) or dict name -> (nf,) bool (:func:`region_masks`).
    ``floor``: the floor facet nearest the axis. ``upper_wall``: the facet with the largest mean
    solar_incident in the first non-empty set of: the equator-facing (or, at the pole, Sun-facing) top
    wall ring, the thesis-style poleward / equatorward upper wall, the poleward rim, the often-lit class;
    else the outermost facet.
    """
    c = np.asarray(run["centroid"].values, float)
    r = np.hypot(c[:, 0], c[:, 1])
    if isinstance(regions, Mapping):
        sets = {k: np.asarray(v, bool) for k, v in regions.items()}
    else:
        regions = np.asarray(regions)
        sets = {k: regions == k for k in np.unique(regions)}
    empty = np.zeros(len(r), bool)
    out = {}
    idx = np.flatnonzero(sets.get("floor", empty))
    if idx.size == 0:
        idx = np.arange(len(r))
    out["floor"] = int(idx[np.argmin(r[idx])])
    solar_name = (
        "solar_incident"
        if io.has_variable(run, "solar_incident")
        else "solar_direct"
        if io.has_variable(run, "solar_direct")
        else None
    )
    mean_solar = np.asarray(run[solar_name].values, float).mean(axis=0) if solar_name else np.zeros(len(r))
    for cand in (
        "top_wall_ring_equator_facing",
        "top_wall_ring_sun_facing",
        "upper_wall_poleward",
        "upper_wall_equatorward",
        "rim_poleward",
        "often_lit",
    ):
        idx = np.flatnonzero(sets.get(cand, empty))
        if idx.size:
            out["upper_wall"] = int(idx[np.argmax(mean_solar[idx])])
            break
    else:
        out["upper_wall"] = int(np.argmax(r))
    return out


def latitude_statistics(
    pairs: Sequence[Tuple[object, object]],
    threshold_K: float = NATURAL_SCATTER_K,
    region_names: Optional[Sequence[str]] = None,
    night_definition: str = regions.DEFAULT_NIGHT,
    min_dark_hours: float = regions.MIN_DARK_HOURS,
) -> Dict[float, dict]:
    """Loose - nominal statistics per latitude and region over several runs (Figs. 7.7b, 7.9).

    Parameters
    ----------
    pairs : sequence of (run, replay) datasets, one per latitude.
    region_names : names from :func:`region_masks` to keep (default all of them).
    night_definition : "dark" (default), "facet", "centre" or "facet_and_centre" (:func:`regions.night_selection`).
    min_dark_hours : float [h], for the per-facet night.

    Returns
    -------
    dict lat_deg -> {"profile": label, "night_definition": str, "night": {region: stats},
    "day": {region: stats}, "night_fallback_facets": {region: int} (facets on the least-lit fallback)}
    """
    out = {}
    for run, replay in pairs:
        io.check_pair(run, replay)
        lab = loose_label(replay, nominal_label(run, replay))
        if lab is None:
            raise FluxFileError("replay has no regolith profile other than the nominal one")
        dT = profile_temperature(replay, lab) - nominal_temperature(run, replay)
        sel = regions.night_selection(run, night_definition, min_dark_hours)
        masks = regions.region_masks(run)
        if region_names is not None:
            masks = {k: masks[k] for k in region_names if k in masks}
        out[io.latitude_deg(run)] = dict(
            profile=lab,
            night_definition=night_definition,
            night=masked_statistics(dT, sel.night, masks, threshold_K),
            day=masked_statistics(dT, sel.day, masks, threshold_K),
            night_fallback_facets={k: int((np.asarray(m, bool) & sel.fallback).sum()) for k, m in masks.items()},
        )
    return out


# ------------------------------------------------------------------------------------ local time


def local_solar_time_h(sun_direction, lat_deg: float) -> np.ndarray:
    """Local solar time [h, 0-24; 12 = noon] at the crater centre from the Sun's direction.

    The Sun vector in the crater frame (x east, y north, z up) is rotated into the Moon-fixed frame of
    the site's meridian; the hour angle H = atan2(-east, -north sin(lat) + up cos(lat)) [rad] (positive in
    the afternoon) gives 12 + 12 H / pi. "Hours" are 1/24 of the lunar (synodic) day. Exact for any
    latitude; at the pole itself it reduces to the Sun's azimuth (noon: Sun toward the far pole's meridian).
    """
    s = sun_direction["sun_direction"].values if hasattr(sun_direction, "attrs") else sun_direction
    s = np.asarray(s, dtype=float)
    if s.ndim != 2 or s.shape[1] != 3:
        raise FluxFileError(f"sun_direction must have shape (time, 3), got {s.shape}")
    phi = np.deg2rad(float(lat_deg))
    ha = np.arctan2(-s[:, 0], -s[:, 1] * np.sin(phi) + s[:, 2] * np.cos(phi))
    return np.mod(12.0 + 12.0 * ha / np.pi, 24.0)
