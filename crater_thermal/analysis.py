"""Analysis of run/replay datasets: night/day, shadow, crater regions, differences, local time.

This module receives datasets (xarray ``Dataset`` objects from :mod:`crater_thermal.io`) and uses
only their mapping interface (``ds["name"].values``, ``ds.attrs``): it does not import xarray.
Every numerical function also works on plain numpy arrays.

Conventions (thesis sections 7.2-7.3, ``shared/design/PHYSICS.md``)
--------------------------------------------------------------------
* **Night / day** is a property of the *time*: night when the centre of the Sun is below the local
  horizon at the crater centre (``sun_direction[:, 2] < 0``), day otherwise. A facet inside a
  permanently shadowed crater is therefore still "in daytime" while the Sun is up: that is the
  thesis's night/day split (Figs. 7.6, 7.7, 7.9). Facets that receive no direct sunlight at a
  time are given separately by :func:`shadow_mask` (``solar_direct == 0``).
* **Regions** come from the facet centroid's distance r from the crater axis and the mesh meta
  (``floor_radius_m``, ``rim_radius_m``, optional ``rim_width_m``):
  ``floor`` r <= floor radius; ``lower_wall`` / ``upper_wall`` the inner and outer halves (in r) of
  the wall between the floor edge and the rim crest; ``rim`` the outer flank from the crest out to
  the plain (rim width from the meta, else Pike 1977: 0.257 D^1.011 km); ``surround`` beyond.
* **Sides**: walls and rim are split by azimuth relative to the pole. The pole direction in the
  crater frame is -y (south) for a southern crater and +y for a northern one. A facet whose
  centroid lies on the pole's side of the axis is ``*_poleward``; its slope faces the *equator*,
  i.e. the Sun, so at -86 deg ``upper_wall_poleward`` is the wall that is lit part of the time and
  ``upper_wall_equatorward`` (facing the pole) never is and behaves like the floor (PHYSICS.md,
  "Where in the crater").
* **Differences** are replayed profile minus nominal profile, per time and facet [K].
  Statistics pool all (time, facet) samples of a region (unweighted by area, as in the thesis).

Instrument model and detection statistics: :mod:`crater_thermal.instrument`.
"""

from __future__ import annotations

import json
from typing import Dict, Iterable, Iterator, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from crater_thermal.constants import LOOSE_PROFILE, NOMINAL_PROFILE
from crater_thermal.errors import ConfigError, FluxFileError

#: Region labels in plotting order (sides: see the module docstring).
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

#: Default |dT| threshold [K] for the "fraction of time above" statistic: the 0.94 K natural scatter.
NATURAL_SCATTER_K = 0.94

#: Variables every analysed run dataset needs.
RUN_VARIABLES = ("time", "surface_temperature", "sun_direction", "centroid", "mesh_faces", "mesh_vertices")
#: Variables every analysed replay dataset needs.
REPLAY_VARIABLES = ("time", "surface_temperature", "profile")


def profile_label(top_bottom: Sequence[float]) -> str:
    """Label of a two-layer profile, e.g. ``(1300.0, 1800.0) -> "1300/1800"``."""
    return f"{top_bottom[0]:g}/{top_bottom[1]:g}"


# ------------------------------------------------------------------------------------ validation


def has_variable(ds, name: str) -> bool:
    """Whether ``ds[name]`` exists (a variable or coordinate of a dataset, a key of a mapping)."""
    try:
        ds[name]
        return True
    except KeyError:
        return False


def check_run(ds, required: Iterable[str] = RUN_VARIABLES) -> None:
    """Raise :class:`FluxFileError` if the run dataset lacks a required variable."""
    missing = [v for v in required if not has_variable(ds, v)]
    if missing:
        raise FluxFileError(f"run dataset is missing variable(s) {', '.join(missing)}; "
                            f"required: {', '.join(required)}")


def check_pair(run, replay) -> None:
    """Check that ``replay`` was made from ``run``: variables present, same mesh hash and time axis.

    Raises
    ------
    FluxFileError
        One line naming what does not match.
    """
    check_run(run)
    missing = [v for v in REPLAY_VARIABLES if not has_variable(replay, v)]
    if missing:
        raise FluxFileError(f"replay dataset is missing variable(s) {', '.join(missing)}; "
                            f"required: {', '.join(REPLAY_VARIABLES)}")
    h_run, h_rep = run.attrs.get("mesh_hash"), replay.attrs.get("mesh_hash")
    if h_run is None or h_rep is None:
        raise FluxFileError("mesh_hash attribute missing from run or replay dataset; cannot check they match")
    if str(h_run) != str(h_rep):
        raise FluxFileError(f"replay mesh_hash={h_rep} does not match run mesh_hash={h_run}; "
                            "the replay must be made from this run")
    t_run = np.asarray(run["time"].values)
    t_rep = np.asarray(replay["time"].values)
    if t_run.shape != t_rep.shape or not np.array_equal(t_run, t_rep):
        raise FluxFileError(f"replay time axis ({t_rep.size} samples) does not match the run's "
                            f"({t_run.size} samples from {t_run[0] if t_run.size else '-'}); "
                            "the replay must cover the run's times")
    dims = tuple(replay["surface_temperature"].dims)
    if dims != ("profile", "time", "facet"):
        raise FluxFileError(f"replay surface_temperature has dims {dims}; expected (profile, time, facet)")
    nf_run = run["surface_temperature"].shape[1]
    if replay["surface_temperature"].shape[2] != nf_run:
        raise FluxFileError(f"replay has {replay['surface_temperature'].shape[2]} facets, run has {nf_run}")


def mesh_meta(ds) -> dict:
    """The ``mesh_meta`` attribute as a dict (JSON string or dict)."""
    meta = ds.attrs.get("mesh_meta", {})
    if isinstance(meta, (str, bytes)):
        try:
            meta = json.loads(meta)
        except ValueError as exc:
            raise FluxFileError(f"mesh_meta attribute is not valid JSON: {exc}") from None
    return dict(meta)


# -------------------------------------------------------------------------------- masks, regions


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
    return classify_regions(ds["centroid"].values, mesh_meta(ds), float(ds.attrs.get("lat_deg", -90.0)),
                            wall_split=wall_split)


# ----------------------------------------------------------------------------------- differences


def nominal_label(ds, replay=None) -> str:
    """Label of the nominal profile: ``attrs["nominal_profile"]`` or the thesis default "1300/1800"."""
    lab = (replay.attrs.get("nominal_profile") if replay is not None else None) or ds.attrs.get("nominal_profile")
    return str(lab) if lab else profile_label(NOMINAL_PROFILE)


def profile_labels(replay) -> List[str]:
    """Profile labels of a replay dataset, as str."""
    return [str(p) for p in np.asarray(replay["profile"].values)]


def find_profile(replay, top: float, bottom: float) -> Optional[str]:
    """Label of the replayed profile with these densities [kg m-3] (by rho_top/rho_bottom or label)."""
    labels = profile_labels(replay)
    if has_variable(replay, "rho_top") and has_variable(replay, "rho_bottom"):
        rt, rb = np.asarray(replay["rho_top"].values, float), np.asarray(replay["rho_bottom"].values, float)
        for lab, a, b in zip(labels, rt, rb):
            if "rock" not in lab.lower() and abs(a - top) < 0.5 and abs(b - bottom) < 0.5:
                return lab
    want = profile_label((top, bottom))
    return want if want in labels else None


def is_rock(label: str) -> bool:
    """True for a rock profile label."""
    return "rock" in str(label).lower()


def nominal_temperature(run, replay=None) -> np.ndarray:
    """(nt, nf) [K] nominal surface temperature: the replayed nominal profile if present, else the run's.

    The replayed nominal uses the same conduction start as the other replayed profiles, so using it
    keeps start-up differences out of the differences.
    """
    if replay is not None:
        lab = nominal_label(run, replay)
        labels = profile_labels(replay)
        if lab not in labels:
            top_bottom = parse_two_layer(lab)
            lab = find_profile(replay, *top_bottom) if top_bottom else None
        if lab is not None:
            return np.asarray(replay["surface_temperature"][labels.index(lab)].values, dtype=float)
    return np.asarray(run["surface_temperature"].values, dtype=float)


def parse_two_layer(label: str) -> Optional[Tuple[float, float]]:
    """``(top, bottom)`` densities [kg m-3] of a two-layer label such as ``"1300/1800"``; None otherwise."""
    try:
        a, b = str(label).split("/")
        return float(a), float(b)
    except ValueError:
        return None


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
    check_pair(run, replay)
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
        if lab != nominal and not is_rock(lab):
            return lab
    return None


def rock_label(replay) -> Optional[str]:
    """The first rock profile label, if any."""
    for lab in profile_labels(replay):
        if is_rock(lab):
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
    return dict(median_K=float(med), q1_K=float(q1), q3_K=float(q3),
                frac_above_threshold=float(np.mean(np.abs(v) > threshold_K)), n=int(v.size))


def region_statistics(dT, time_mask, regions, threshold_K: float = NATURAL_SCATTER_K,
                      region_names: Sequence[str] = REGIONS) -> Dict[str, dict]:
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
    if has_variable(replay, "rho_top") and has_variable(replay, "rho_bottom"):
        rt = np.asarray(replay["rho_top"].values, float)
        rb = np.asarray(replay["rho_bottom"].values, float)
    else:
        pairs = [parse_two_layer(lab) or (np.nan, np.nan) for lab in labels]
        rt, rb = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    keep = [i for i, lab in enumerate(labels) if not is_rock(lab) and np.isfinite(rt[i]) and np.isfinite(rb[i])]
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


def density_grid_medians(replay, diffs: Mapping[str, np.ndarray], night, facet_mask,
                         nominal: Optional[str] = None):
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
        med = {lab: float(np.median(np.asarray(d)[night][:, fm])) for lab, d in diffs.items() if not is_rock(lab)}
    return density_grid(replay, med, nominal)


def representative_facets(run, regions) -> Dict[str, int]:
    """Facets for time-series figures (thesis Figs. 7.4-7.6).

    ``floor``: the floor facet nearest the axis. ``upper_wall``: the upper-wall facet with the largest
    mean solar_incident (the Sun-facing, poleward wall), from any upper wall if none is lit.
    """
    c = np.asarray(run["centroid"].values, float)
    r = np.hypot(c[:, 0], c[:, 1])
    regions = np.asarray(regions)
    out = {}
    idx = np.flatnonzero(regions == "floor")
    if idx.size == 0:
        idx = np.arange(len(r))
    out["floor"] = int(idx[np.argmin(r[idx])])
    solar_name = ("solar_incident" if has_variable(run, "solar_incident")
                  else "solar_direct" if has_variable(run, "solar_direct") else None)
    mean_solar = (np.asarray(run[solar_name].values, float).mean(axis=0) if solar_name
                  else np.zeros(len(r)))
    for cand in ("upper_wall_poleward", "upper_wall_equatorward", "rim_poleward"):
        idx = np.flatnonzero(regions == cand)
        if idx.size:
            out["upper_wall"] = int(idx[np.argmax(mean_solar[idx])])
            break
    else:
        out["upper_wall"] = int(np.argmax(r))
    return out


def latitude_statistics(pairs: Sequence[Tuple[object, object]], threshold_K: float = NATURAL_SCATTER_K,
                        region_names: Sequence[str] = REGIONS) -> Dict[float, dict]:
    """Loose - nominal statistics per latitude and region over several runs (Figs. 7.7b, 7.9).

    Parameters
    ----------
    pairs : sequence of (run, replay) datasets, one per latitude.

    Returns
    -------
    dict lat_deg -> {"profile": label, "night": {region: stats}, "day": {region: stats}}
    """
    out = {}
    for run, replay in pairs:
        check_pair(run, replay)
        lab = loose_label(replay, nominal_label(run, replay))
        if lab is None:
            raise FluxFileError("replay has no regolith profile other than the nominal one")
        dT = profile_temperature(replay, lab) - nominal_temperature(run, replay)
        night = night_mask(run)
        reg = regions_of(run)
        out[float(run.attrs.get("lat_deg", np.nan))] = dict(
            profile=lab,
            night=region_statistics(dT, night, reg, threshold_K, region_names),
            day=region_statistics(dT, ~night, reg, threshold_K, region_names),
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
