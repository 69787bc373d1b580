"""Report of a run and its replay: figures (thesis Figs. 7.4-7.9 analogues), report.html, summary.json.

``make_report(run, replay, out_dir)`` writes

* ``out_dir/figures/*.png`` (:data:`FIGURES`), matplotlib (object API, Agg canvas) and, when
  rendering works, 3-D crater snapshots from :mod:`crater_thermal.viz`;
* ``out_dir/report.html``: self-contained (PNGs embedded as base64), readable offline;
* ``out_dir/summary.json``: the keys documented in :data:`SUMMARY_KEYS` (units in the key names).

Each of the three is written through :func:`crater_thermal.io.atomic_output` and moved into place
only when everything is done, ``report.html`` last; an existing report is refused unless
``overwrite=True``. Without pyvista (the ``viz`` extra) the 3-D snapshots are skipped with a note.
The analysis itself lives in :mod:`crater_thermal.analysis`.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import html
import json
import math
import os
import sys
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from crater_thermal import analysis as an
from crater_thermal import answer, profiles, regions
from crater_thermal import instrument as ins
from crater_thermal import inversion as inv
from crater_thermal import io as ctio
from crater_thermal.errors import ConfigError, CraterThermalError, MissingExtraError
from crater_thermal.progress import bar

#: Figure files written to ``figures/`` (3-D snapshots are added when rendering works).
FIGURES = {
    "fig7_4_incident_flux.png": (
        "Solar (direct + scattered) vs emitted-IR incident flux on a floor and an upper-wall facet (thesis Fig. 7.4)."
    ),
    "fig7_5_temperature.png": (
        "Surface temperature of nominal regolith, loose regolith and rock on the same facets (Fig. 7.5)."
    ),
    "fig7_6_loose_minus_nominal.png": "Loose minus nominal surface temperature over the run, night shaded (Fig. 7.6).",
    "fig7_7a_density_grid.png": (
        "Night-time median difference to nominal on the floor over the density grid, top x bottom density; "
        "nominal outlined (Fig. 7.7a)."
    ),
    "fig7_7b_regions.png": "Night-time (per facet) median loose minus nominal by crater region and illumination class "
    "(and latitude), bars = quartiles (Fig. 7.7b).",
    "fig7_8_night_map.png": "Plan view: per-facet night-time median |loose minus nominal| over the crater (Fig. 7.8).",
    "fig7_9_quartiles.png": (
        "Quartiles of loose minus nominal at night and by day, per region or per latitude (Fig. 7.9)."
    ),
    "detectability.png": "Probability of detecting loose vs nominal (night medians) against dwell time, per "
    "instrument and region, at the stated false-alarm rate (instrument.py).",
    "detection_local_time.png": "Signal-to-noise |dT|/sigma against local solar time per region (best instrument), "
    "at the reference dwell.",
    "detectability_scatter.png": "Time on each footprint needed for P_D >= 0.9 against the natural scatter between "
    "footprints, per instrument, on the headline's region (a missing point: not detectable at that scatter); "
    "the dashed line is the scatter the report assumes.",
}
#: Figures drawn only when the replay is a density grid (captions, as FIGURES)
INVERSION_FIGURES = {
    "inversion_design.png": "Observation design for the inversion (crater-thermal invert), on the floor facet "
    "most sensitive to density: expected posterior sd of the bottom density from one sample versus hours into "
    "the night (60 s dwell), and expected P(loose) of a loose footprint seen at three local times versus the "
    "dwell of each sample.",
}
SNAPSHOTS = {
    "map3d_temperature.png": (
        "3-D view: nominal surface temperature at the time of the highest Sun, with the Sun direction."
    ),
    "map3d_night_dT.png": "3-D view: per-facet night-time median loose minus nominal.",
}

#: Top-level keys of summary.json and what they hold (units in the names; regions: regions.region_masks).
SUMMARY_KEYS = {
    "schema_version": "int: layout version of this file (2: detection statistics replace the k-sigma "
    "detectability of 1).",
    "mesh_hash": "str: mesh hash shared by the run and the replay.",
    "lat_deg": "float [deg]: latitude of the crater (first run if several).",
    "lon_deg": "float [deg]: longitude of the crater.",
    "time_start_utc": "str: first sample, ISO UTC.",
    "time_end_utc": "str: last sample, ISO UTC.",
    "n_times": "int: number of time samples.",
    "n_facets": "int: number of mesh facets.",
    "night_fraction": "float [-]: fraction of samples with the Sun's centre below the horizon at the crater centre.",
    "night_definition": "str: 'dark' (night = no sunlight, direct or scattered, on the facet for "
    "night_min_dark_hours; day = the facet receives sunlight), 'facet' (no direct sunlight; day = directly lit), "
    "'centre' (the thesis: Sun's centre below the crater centre's horizon) or 'facet_and_centre'.",
    "night_min_dark_hours": "float [h]: darkness a facet needs before its samples count as night (per facet).",
    "night_threshold_W_m2": "float|null [W m-2]: flux at or below which a facet counts as unlit (solar_incident "
    "for 'dark', solar_direct for 'facet'; null for 'centre').",
    "night_fallback_fraction": "float|null [-]: 'dark' only: a facet with fewer dark night samples than this "
    "fraction of the record uses this fraction of its least-lit samples without direct sunlight instead.",
    "night_fallback_facets": "int: facets whose night is that least-lit fallback (0 unless 'dark' and a facet is "
    "never dark long enough, e.g. a floor near the pole).",
    "night_fallback_facets_by_region": "{region: int}: the same, per region.",
    "night_fraction_samples": "float [-]: fraction of (time, facet) samples that are night.",
    "regions": "list[str]: region names (regions.region_masks): floor, {lower_wall, upper_wall, top_wall_ring, rim}_"
    "{pole,equator,east,west}_facing (by the facet normal's azimuth, +-45 deg; at |lat| >= 89.5 deg "
    "{antisun,sun,sun_left,sun_right}_facing), surround, never_lit / rarely_lit / often_lit; may overlap.",
    "region_facet_count": "{region: int}: facets per region.",
    "site": "dict|null: the DEM site (dem_source, crs_name, center_lat/lon_deg, radius_km, resolution_m, "
    "outer_radius_km, outer_resolution_m, height_kind, dem_pixel_m, n_inner, n_outer); null for craters.",
    "profiles": "list[str]: replayed profile labels.",
    "nominal_profile": "str: the nominal profile label (differences are profile minus this).",
    "loose_profile": "str|null: the loose profile label (800/1100 if replayed).",
    "rock_profile": "str|null: the rock profile label, if replayed.",
    "threshold_K": "float [K]: |dT| threshold for the *_frac_abs_dT_above_threshold statistics.",
    "night_median_dT_K": (
        "{profile: {region: float|null}} [K]: median of profile minus nominal over night samples and region facets."
    ),
    "night_q1_dT_K": "{profile: {region: float|null}} [K]: first quartile, night.",
    "night_q3_dT_K": "{profile: {region: float|null}} [K]: third quartile, night.",
    "day_median_dT_K": "{profile: {region: float|null}} [K]: median, day (night_definition: facet directly lit, "
    "or Sun above the crater centre's horizon).",
    "day_q1_dT_K": "{profile: {region: float|null}} [K]: first quartile, day.",
    "day_q3_dT_K": "{profile: {region: float|null}} [K]: third quartile, day.",
    "night_frac_abs_dT_above_threshold": (
        "{profile: {region: float|null}} [-]: fraction of night samples with |dT| > threshold_K."
    ),
    "night_median_T_nominal_K": "{region: float|null} [K]: night-time median nominal surface temperature.",
    "max_abs_night_median_dT_K": "{profile: float} [K]: largest per-facet |night-time median difference|.",
    "density_grid_floor_night_median_dT_K": (
        "{rho_top_kg_m3: [..], rho_bottom_kg_m3: [..], dT_K: [[..]] (null where not replayed)}: night medians "
        "over the density grid on density_grid_region (Fig. 7.7a; the crater floor, on a DEM site a class)."
    ),
    "density_grid_region": "str|null: the region the density grid is summarized on (report.GRID_REGIONS).",
    "latitude_night_median_dT_K": (
        "{lat_deg (str): {region: float|null}} [K]: loose minus nominal night median per run latitude."
    ),
    "latitude_day_median_dT_K": (
        "{lat_deg (str): {region: float|null}} [K]: loose minus nominal day median per run latitude."
    ),
    "latitude_detection_dwell_s": "{lat_deg (str): {instrument: {region: float|null}}} [s]: dwell on each "
    "footprint for P_D >= target per latitude (null = not detectable at any dwell).",
    "instruments": "{name: {name, lo_um, hi_um, netd_ref_K, t_ref_K, integration_s, knee_s, gain_error, source, "
    "pass_integration_s (orbital pushbroom [s] per pass, null = staring)}}: "
    "instrument channels (instrument.Instrument; presets instrument.PRESETS).",
    "observation": "{footprint_fraction, reference_footprints, natural_scatter_K [K], false_alarm, target_pd, "
    "candidate_footprints (k), patch_area_m2 [m2], footprint_area_m2 [m2] (null = k given), mode (auto | stare | "
    "passes), passes (of the stated observation), pass_integration_s [s] (null = the instrument's), test, "
    "mode_by_instrument {instrument: stare | passes}, pass_integration_s_by_instrument {instrument: [s] | null}}: "
    "how the candidate patch is compared with nominal (instrument.Observation).",
    "detection_reference_dwell_s": "float [s]: stare dwell at which |dT|/sigma is evaluated for the best local "
    "time (instruments in pass mode: observation.passes).",
    "detection_dwell_grid_s": "{instrument: [float]} [s]: total time on each footprint of the P_D curves' "
    "exposures (pass mode: whole passes x pass_integration_s).",
    "band_signal_night_floor": "{instrument: {band_um, T_K, band_radiance_W_m2_sr, dL_dT_W_m2_sr_K, netd_K, "
    "netd_ref_K, t_ref_K}}: what each band receives from the night-time nominal floor "
    "(and at 300 K).",
    "detection": "{instrument: {region: {dT_median_K, dT_q1_K, dT_q3_K, T_nominal_K, mu_K (observed, band-mixed), "
    "netd_candidate_K, netd_reference_K, mode (stare | passes), exposure_unit (s | passes), pass_integration_s, "
    "detectable, exposure (dwell [s] or passes; null = none), dwell_s (total time on each footprint [s], "
    "null = none), passes (null in a stare), n_samples, threshold_K, pd_at_dwell, "
    "pd_limit (infinite dwell), limiting_term (instrument.TERMS), sigma_terms_K {term: K}, answer "
    "(sentence), pd_vs_dwell [-] on detection_dwell_grid_s, best_local_time_h (null = no samples), "
    "best_snr, best_dT_K, best_T_nominal_K, snr_by_local_time [-] (24 lunar-hour bins, |mu|/sigma_0 at "
    "detection_reference_dwell_s), dwell_s_scatter_half, dwell_s_scatter_double, dwell_s_no_scatter "
    "(the band alone: null = the instrument cannot see it)}}}: loose vs nominal "
    "from night-time medians (instrument.dwell_for_detection).",
    "figures": "list[str]: files written under figures/.",
    "snapshot_note": "str|null: why 3-D snapshots are missing, if they are.",
    "headline": "str: the answer in plain words (answer.headline of this summary): the report's first paragraph, "
    "printed by `report` and `summary`.",
    "detectability_vs_scatter": "{region, scatter_K [K], dwell_s {instrument: [s|null]}, exposure {instrument: "
    "[s|passes|null]}, exposure_unit {instrument: s|passes}}|null: the exposure for P_D >= target_pd on the "
    "headline's region (answer.focus_region) as the natural scatter runs over SCATTER_SWEEP_K (null: not "
    "detectable at that scatter).",
    "inversion_design": "{facet (of region: the one whose night median differs most over the replayed "
    "profiles), region, truth_kg_m3 [top, bottom], loose_bottom_kg_m3, prior_sd_kg_m3 [top, "
    "bottom], prior_p_loose, natural_scatter_K, single_sample_dwell_s, hours_into_night [h] (since that night's "
    "first sample in the record), local_times_h [h], "
    "dwell_s [s], by_instrument {instrument: {sd_top_kg_m3, sd_bottom_kg_m3 (one sample at each of "
    "hours_into_night), best_hours_into_night, p_loose, sd_bottom_three_local_times_kg_m3 (three samples at "
    "local_times_h, each dwell of dwell_s), dwell_for_95pct_s (shortest dwell reaching 95 % of the longest's "
    "expected P(loose); null: the data leave P(loose) at the prior's)}}}|null: expected posterior widths of the "
    "inversion (inversion.expected_width: the posterior of noiseless data of the truth, the loose profile "
    "clipped into the grid) on that facet's longest night; null without a complete regular density grid.",
    "detection_larger_patch": "{candidate_footprints, reference_footprints, region, by_instrument {instrument: "
    "{detectable, exposure, exposure_unit, dwell_s, passes, pd_limit}}}|null: the same test for a loose patch of "
    "LARGER_PATCH footprints against as many references (the patch size a rover team asks about).",
}

#: Natural scatter values [K] of the detectability-versus-scatter figure and summary entry: its plausible range
#: (Diviner's 0.94 K was measured at 70-120 K outside the polar craters; half and twice that bracket it).
SCATTER_SWEEP_K = tuple(round(0.2 + 0.1 * i, 2) for i in range(19))
#: Footprints of the larger loose patch the summary also tests (k = m; thesis: one footprint against one).
LARGER_PATCH = 3

PathOrDs = Union[str, os.PathLike, object]


# ------------------------------------------------------------------------------------ summary


def _clean(x):
    """JSON-safe: numpy scalars to Python, NaN/inf to None, keys to str."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_clean(v) for v in (x.tolist() if isinstance(x, np.ndarray) else x)]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


#: Where a density grid is summarized when there is no crater floor (a DEM site), in order of preference:
#: the facets never in direct sunlight (a PSR: the rover's question), else level ground.
GRID_REGIONS = ("floor", "never_lit", "level", "slope_0_5_deg")


def grid_region(regions: Dict[str, np.ndarray]) -> Optional[str]:
    """The region whose night medians the density grid shows: the first non-empty of :data:`GRID_REGIONS`,
    else the largest region (None without regions)."""
    for name in GRID_REGIONS:
        if name in regions and np.any(regions[name]):
            return name
    return max(regions, key=lambda r: int(np.sum(regions[r])), default=None)


class _Analysis:
    """Everything the figures and the summary need, computed once."""

    def __init__(
        self,
        run,
        replay,
        threshold_K: float,
        advance: Callable[[], None] = lambda: None,
        night_definition: str = regions.DEFAULT_NIGHT,
        min_dark_hours: float = regions.MIN_DARK_HOURS,
    ):
        ctio.check_pair(run, replay)
        self.run, self.replay = run, replay
        self.times = np.asarray(run["time"].values).astype("datetime64[ns]")
        self.days = (self.times - self.times[0]).astype(np.int64) / 86400e9
        self.night = regions.night_mask(run)  # the crater centre's night: shading of the time series
        self.night_definition, self.min_dark_hours = night_definition, float(min_dark_hours)
        # per (time, facet) night and day used by every statistic (regions.night_day_masks)
        self.night_sel = regions.night_selection(run, night_definition, min_dark_hours)
        self.night_f, self.day_f = self.night_sel.night, self.night_sel.day
        self.regions = regions.region_masks(run)  # name -> (nf,) bool
        self.nf = int(run["surface_temperature"].shape[1])
        self.local_time = an.local_solar_time_h(run, ctio.latitude_deg(run))
        self.meta = ctio.mesh_meta(run)
        self.lat = ctio.latitude_deg(run)
        self.nominal = an.nominal_label(run, replay)
        self.labels = an.profile_labels(replay)
        self.loose = an.loose_label(replay, self.nominal)
        self.rock = an.rock_label(replay)
        self.T_nom = an.nominal_temperature(run, replay)
        self.threshold = threshold_K
        self.facets = an.representative_facets(run, self.regions)
        self.grid_region = grid_region(self.regions)  # where the density grid is summarized (Fig. 7.7a)
        # one profile at a time: keep small results, and the full difference only for the loose profile
        self.night_stats, self.day_stats, self.night_map, self.floor_night_median = {}, {}, {}, {}
        self.loose_dT = None
        for p, d in an.iter_profile_differences(run, replay, self.T_nom):
            self.night_stats[p] = an.masked_statistics(d, self.night_f, self.regions, threshold_K)
            self.day_stats[p] = an.masked_statistics(d, self.day_f, self.regions, threshold_K)
            self.night_map[p] = an.facet_median_map(d, self.night_f)
            self.floor_night_median[p] = self.night_stats[p].get(self.grid_region, {}).get("median_K")
            if p == self.loose:
                self.loose_dT = d
            advance()
        self.nom_night = {r: an.masked_median(self.T_nom, self.night_f, m) for r, m in self.regions.items()}

    def region_label(self, i: int) -> str:
        """The first crater region (or class) holding facet ``i``."""
        return next((r for r, m in self.regions.items() if m[i]), "-")

    def profile_T(self, label):
        return an.profile_temperature(self.replay, label)

    def density_grid(self):
        return an.density_grid(
            self.replay, {p: v for p, v in self.floor_night_median.items() if not profiles.is_rock(p)}, self.nominal
        )


# ---------------------------------------------------------------------------------- detection

#: Dwell [s] at which |dT|/sigma is compared across local times (the thesis's one-minute stop, 8.5)
REFERENCE_DWELL_S = 60.0
_LT_BINS = 24


def _local_time_bins(A, r) -> Tuple[np.ndarray, np.ndarray]:
    """Per lunar-hour bin (24) medians of loose - nominal [K] and of nominal T [K] in region r (NaN if empty)."""
    cols = A.regions[r]
    dT, Tn = np.full(_LT_BINS, np.nan), np.full(_LT_BINS, np.nan)
    if A.loose is None or not cols.any():
        return dT, Tn
    b = np.clip(np.floor(A.local_time * _LT_BINS / 24.0), 0, _LT_BINS - 1)
    for j in range(_LT_BINS):
        tm = b == j
        if tm.any():
            dT[j] = np.median(A.loose_dT[tm][:, cols])
            Tn[j] = np.median(A.T_nom[tm][:, cols])
    return dT, Tn


def _best_local_time(bins, inst: ins.Instrument, obs: ins.Observation) -> dict:
    """Local-time bin (1 lunar hour) where |observed dT| / sigma_0 at the reference dwell peaks."""
    dT, Tn = bins
    snr = np.full(_LT_BINS, np.nan)
    ok = np.isfinite(dT) & np.isfinite(Tn) & (Tn > 0) & (Tn + dT > 0)
    if ok.any():
        mu, _ = ins.observed_difference(dT[ok], Tn[ok], inst, obs)
        snr[ok] = np.abs(mu) / ins.sigma_null(Tn[ok], ins.stated_exposure(inst, obs, REFERENCE_DWELL_S), inst, obs)
    if not np.isfinite(snr).any():
        return dict(best_local_time_h=None, best_snr=None, best_dT_K=None, best_T_nominal_K=None, snr_by_local_time=snr)
    j = int(np.nanargmax(snr))
    return dict(
        best_local_time_h=(j + 0.5) * 24.0 / _LT_BINS,
        best_snr=float(snr[j]),
        best_dT_K=float(dT[j]),
        best_T_nominal_K=float(Tn[j]),
        snr_by_local_time=snr,
    )


def _detection(A, instruments: Sequence[ins.Instrument], obs: ins.Observation, with_time: bool = True) -> dict:
    """{instrument: {region: ...}} loose vs nominal from the night-time medians (SUMMARY_KEYS["detection"])."""
    out = {}
    bins = {r: _local_time_bins(A, r) for r in A.regions} if with_time else {}
    for inst in instruments:
        grid = ins.exposure_grid(inst, obs)
        per = {}
        for r in A.regions:
            st = A.night_stats[A.loose][r] if A.loose is not None else {}
            med, Tn = st.get("median_K"), A.nom_night.get(r)
            row = dict(dT_median_K=med, dT_q1_K=st.get("q1_K"), dT_q3_K=st.get("q3_K"), T_nominal_K=Tn)
            if med is None or Tn is None or not Tn + med > 0:
                row.update(
                    detectable=False, dwell_s=None, answer="no night-time samples", pd_vs_dwell=None, limiting_term=None
                )
                per[r] = row
                continue
            row.update(ins.dwell_for_detection(med, Tn, inst, obs))
            row["pd_vs_dwell"] = ins.detection_probability(med, Tn, grid, inst, obs)
            for key, f in (("dwell_s_scatter_half", 0.5), ("dwell_s_scatter_double", 2.0), ("dwell_s_no_scatter", 0.0)):
                o = obs.with_scatter(f * obs.natural_scatter_K)
                row[key] = ins.dwell_for_detection(med, Tn, inst, o)["dwell_s"]
            if with_time:
                row.update(_best_local_time(bins[r], inst, obs))
            per[r] = row
        out[inst.name] = per
    return out


def _stat(stats, key):
    return {p: {r: s[key] for r, s in by_region.items()} for p, by_region in stats.items()}


def _summary(
    A: _Analysis,
    others: Sequence[_Analysis],
    instruments: Sequence[ins.Instrument],
    obs: ins.Observation,
    figures: List[str],
    snapshot_note: Optional[str],
) -> dict:
    nom_night = A.nom_night
    tops, bottoms, grid = A.density_grid()
    det = _detection(A, instruments, obs)
    T_floor = nom_night.get("floor") or next((v for v in nom_night.values() if v), None)
    band_T = [T_floor, 300.0] if T_floor else [300.0]
    lat_night, lat_day, lat_dwell = {}, {}, {}
    for B in [A, *others]:
        if B.loose is None:
            continue
        key = f"{B.lat:g}"
        lat_night[key] = {r: B.night_stats[B.loose][r]["median_K"] for r in B.regions}
        lat_day[key] = {r: B.day_stats[B.loose][r]["median_K"] for r in B.regions}
        b_det = det if B is A else _detection(B, instruments, obs, with_time=False)
        lat_dwell[key] = {i: {r: v["dwell_s"] for r, v in per.items()} for i, per in b_det.items()}
    s = dict(
        schema_version=2,
        site=site_summary(A),
        mesh_hash=str(A.run.attrs.get("mesh_hash")),
        lat_deg=A.lat,
        lon_deg=float(A.run.attrs.get("lon_deg", np.nan)),
        time_start_utc=str(np.datetime_as_string(A.times[0], unit="s")) + "Z",
        time_end_utc=str(np.datetime_as_string(A.times[-1], unit="s")) + "Z",
        n_times=int(A.times.size),
        n_facets=A.nf,
        night_fraction=float(A.night.mean()),
        night_definition=A.night_definition,
        night_min_dark_hours=A.min_dark_hours,
        night_threshold_W_m2=A.night_sel.threshold_W_m2,
        night_fallback_fraction=A.night_sel.fallback_fraction,
        night_fallback_facets=int(A.night_sel.fallback.sum()),
        night_fallback_facets_by_region={r: int((m & A.night_sel.fallback).sum()) for r, m in A.regions.items()},
        night_fraction_samples=float(A.night_f.mean()),
        regions=list(A.regions),
        region_facet_count={r: int(m.sum()) for r, m in A.regions.items()},
        profiles=list(A.labels),
        nominal_profile=A.nominal,
        loose_profile=A.loose,
        rock_profile=A.rock,
        threshold_K=A.threshold,
        night_median_dT_K=_stat(A.night_stats, "median_K"),
        night_q1_dT_K=_stat(A.night_stats, "q1_K"),
        night_q3_dT_K=_stat(A.night_stats, "q3_K"),
        day_median_dT_K=_stat(A.day_stats, "median_K"),
        day_q1_dT_K=_stat(A.day_stats, "q1_K"),
        day_q3_dT_K=_stat(A.day_stats, "q3_K"),
        night_frac_abs_dT_above_threshold=_stat(A.night_stats, "frac_above_threshold"),
        night_median_T_nominal_K=nom_night,
        max_abs_night_median_dT_K={
            p: float(np.nanmax(np.abs(m))) if np.isfinite(m).any() else None for p, m in A.night_map.items()
        },
        density_grid_floor_night_median_dT_K=dict(rho_top_kg_m3=tops, rho_bottom_kg_m3=bottoms, dT_K=grid),
        density_grid_region=A.grid_region,
        latitude_night_median_dT_K=lat_night,
        latitude_day_median_dT_K=lat_day,
        latitude_detection_dwell_s=lat_dwell,
        instruments={i.name: i.as_dict() for i in instruments},
        observation=obs.as_dict(instruments),
        detection_reference_dwell_s=REFERENCE_DWELL_S,
        detection_dwell_grid_s={i.name: ins.exposure_seconds(ins.exposure_grid(i, obs), i, obs) for i in instruments},
        band_signal_night_floor=ins.band_table(band_T, instruments),
        detection=det,
        figures=list(figures),
        snapshot_note=snapshot_note,
    )
    s = _clean(s)
    focus = answer.focus_region(s)
    s["detectability_vs_scatter"] = _clean(_scatter_sweep(s, focus, instruments, obs))
    s["detection_larger_patch"] = _clean(_larger_patch(s, focus, instruments, obs))
    s["inversion_design"] = _clean(inversion_design(A, instruments, obs))
    s["headline"] = answer.headline(s)  # from the cleaned numbers: the headline says what summary.json says
    assert set(s) == set(SUMMARY_KEYS), set(s) ^ set(SUMMARY_KEYS)
    return s


#: Dwell [s] of each sample in the three-local-times design of ``inversion_design``
DESIGN_DWELLS_S = (1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)
#: Most single-sample times of night evaluated by ``inversion_design`` (cost: one footprint each)
DESIGN_MAX_TIMES = 24


def _grid_forward(A, facet: int) -> Optional[inv.ForwardModel]:
    """ForwardModel of the replay's two-layer profiles on one facet, or None unless they fill a regular grid
    (>= 3 densities per layer, every top <= bottom node)."""
    tops = np.asarray(A.replay["rho_top"].values, float)
    bots = np.asarray(A.replay["rho_bottom"].values, float)
    two = np.isfinite(tops) & np.isfinite(bots) & (tops < 3000) & (bots < 3000)
    # the grid's profiles: densities used by >= 2 profiles (drops a lone nominal or loose profile replayed
    # beside a grid off its nodes), each (top, bottom) pair once
    vals, counts = np.unique(np.r_[tops[two], bots[two]], return_counts=True)
    common = set(vals[counts >= 2].tolist())
    keep, seen = [], set()
    for i in np.flatnonzero(two):
        pair = (float(tops[i]), float(bots[i]))
        if pair[0] in common and pair[1] in common and pair not in seen:
            keep.append(i)
            seen.add(pair)
    keep = np.asarray(keep, np.int64)
    if keep.size < 6:
        return None
    T = np.asarray(A.replay["surface_temperature"].isel(facet=facet).values, np.float32)[keep][:, :, None]
    try:
        fm = inv.ForwardModel(T, tops[keep], bots[keep], A.times)
    except ConfigError:
        return None
    P = fm.node_profile
    need = fm.top_nodes[:, None] <= fm.bottom_nodes[None, :]
    if min(P.shape) < 3 or np.any((P < 0) & need):
        return None
    return fm


def _design_facet(A) -> int:
    """The facet of the grid's region (the floor) whose night-time median differs most from nominal over the
    replayed profiles: where the inversion has most to see (the representative floor facet if none differs)."""
    region = A.regions.get(A.grid_region) if A.grid_region else None
    maps = [np.abs(np.asarray(m, float)) for p, m in A.night_map.items() if not profiles.is_rock(p)]
    if region is None or not np.any(region) or not maps:
        return int(A.facets.get("floor", 0))
    stack = np.stack(maps)
    spread = np.where(np.isfinite(stack), stack, -1.0).max(axis=0)  # -1: no night value on that facet
    idx = np.flatnonzero(region)
    if spread[idx].max() < 0:
        return int(A.facets.get("floor", 0))
    return int(idx[int(np.argmax(spread[idx]))])


def inversion_design(A, instruments: Sequence[ins.Instrument], obs: ins.Observation) -> Optional[dict]:
    """Expected posterior width of the inversion versus time of night and dwell (SUMMARY_KEYS), or None."""
    facet = _design_facet(A)
    fm = _grid_forward(A, facet)
    night = np.flatnonzero(np.asarray(A.night_f[:, facet], bool))
    if fm is None or night.size < 3:
        return None
    # the longest run of consecutive night samples: one night, from its first sample
    breaks = np.flatnonzero(np.diff(night) > 1)
    starts, ends = np.r_[0, breaks + 1], np.r_[breaks, night.size - 1]
    i = int(np.argmax(ends - starts))
    one_night = night[starts[i] : ends[i] + 1]
    t_h = (fm.times[one_night] - fm.times[one_night[0]]).astype("timedelta64[s]").astype(float) / 3600.0
    pick = np.unique(np.linspace(0, one_night.size - 1, min(DESIGN_MAX_TIMES, one_night.size)).round().astype(int))
    three = np.unique(np.linspace(0, one_night.size - 1, 5).round().astype(int)[1:4])
    ta, ba = fm.top_nodes, fm.bottom_nodes
    top = float(np.clip(800.0, ta[0], ta[-1]))
    truth = (top, float(np.clip(max(1100.0, top), ba[0], ba[-1])))
    by = {}
    common = dict(truth_kg_m3=truth, natural_scatter_K=obs.natural_scatter_K)
    for inst in instruments:
        one = inv.expected_width(fm, 0, [fm.times[one_night[[k]]] for k in pick], [REFERENCE_DWELL_S], inst, **common)
        des = inv.expected_width(fm, 0, [fm.times[one_night[three]]], DESIGN_DWELLS_S, inst, **common)
        p = des["p_loose"][0]
        informative = abs(p[-1] - des["prior_p_loose"]) > 0.05
        ok = np.flatnonzero(p >= 0.95 * p[-1])
        by[inst.name] = dict(
            sd_top_kg_m3=one["sd_top_kg_m3"][:, 0],
            sd_bottom_kg_m3=one["sd_bottom_kg_m3"][:, 0],
            best_hours_into_night=float(t_h[pick][int(np.argmin(one["sd_bottom_kg_m3"][:, 0]))]),
            p_loose=p,
            sd_bottom_three_local_times_kg_m3=des["sd_bottom_kg_m3"][0],
            dwell_for_95pct_s=float(DESIGN_DWELLS_S[ok[0]]) if informative and ok.size else None,
        )
    return dict(
        facet=facet,
        region=A.grid_region,
        truth_kg_m3=list(truth),
        loose_bottom_kg_m3=inv.LOOSE_BOTTOM_KG_M3,
        prior_sd_kg_m3=des["prior_sd_kg_m3"],
        prior_p_loose=des["prior_p_loose"],
        natural_scatter_K=obs.natural_scatter_K,
        single_sample_dwell_s=REFERENCE_DWELL_S,
        hours_into_night=t_h[pick],
        local_times_h=t_h[three],
        dwell_s=list(DESIGN_DWELLS_S),
        by_instrument=by,
    )


def _fig_inversion_design(summary: dict, path) -> None:
    d = summary["inversion_design"]
    fig, axes = _figure(1, 2, size=(11.0, 4.2))
    ax = axes[0]
    for name, v in d["by_instrument"].items():
        ax[0].plot(d["hours_into_night"], v["sd_bottom_kg_m3"], ".-", label=name)
        ax[1].semilogx(d["dwell_s"], v["p_loose"], "o-", label=name)
    ax[0].axhline(d["prior_sd_kg_m3"][1], color="k", ls=":", label="prior")
    ax[1].axhline(d["prior_p_loose"], color="k", ls=":", label="prior")
    t, b = d["truth_kg_m3"]
    ax[0].set(
        xlabel="hours into the night [h]",
        ylabel="expected posterior sd, bottom [kg m-3]",
        title=f"one {d['single_sample_dwell_s']:g} s sample, facet {d['facet']}",
    )
    ax[1].set(
        xlabel="dwell per sample [s]",
        ylabel=f"expected P(bottom < {d['loose_bottom_kg_m3']:g} kg m-3)",
        ylim=(0, 1),
        title=f"truth {t:g}/{b:g}, three local times",
    )
    for a in ax:
        a.legend(fontsize=8)
    fig.savefig(path)


def _focus_values(s: dict, focus: Optional[str]):
    """(night median loose - nominal [K], nominal night temperature [K]) of the headline's region, or None."""
    if focus is None or not s.get("loose_profile"):
        return None
    dT = s["night_median_dT_K"][s["loose_profile"]].get(focus)
    Tn = s["night_median_T_nominal_K"].get(focus)
    return None if dT is None or not Tn or not Tn + dT > 0 else (dT, Tn)


def _scatter_sweep(s: dict, focus, instruments, obs: ins.Observation) -> Optional[dict]:
    """Exposure for P_D >= target on the headline's region across :data:`SCATTER_SWEEP_K` (summary key)."""
    vals = _focus_values(s, focus)
    if vals is None:
        return None
    out = {"region": focus, "scatter_K": list(SCATTER_SWEEP_K), "dwell_s": {}, "exposure": {}, "exposure_unit": {}}
    for inst in instruments:
        rows = [ins.dwell_for_detection(*vals, inst, obs.with_scatter(x)) for x in SCATTER_SWEEP_K]
        out["dwell_s"][inst.name] = [r["dwell_s"] for r in rows]
        out["exposure"][inst.name] = [r["exposure"] for r in rows]
        out["exposure_unit"][inst.name] = rows[0]["exposure_unit"]
    return out


def _larger_patch(s: dict, focus, instruments, obs: ins.Observation) -> Optional[dict]:
    """The detection test for a loose patch of :data:`LARGER_PATCH` footprints against as many references."""
    vals = _focus_values(s, focus)
    if vals is None:
        return None
    k = LARGER_PATCH
    m = max(k, obs.reference_footprints)
    o = dataclasses.replace(
        obs, candidate_footprints=k, reference_footprints=m, patch_area_m2=None, footprint_area_m2=None
    )
    keys = ("detectable", "exposure", "exposure_unit", "dwell_s", "passes", "pd_limit", "pass_integration_s")
    by = {inst.name: {key: ins.dwell_for_detection(*vals, inst, o).get(key) for key in keys} for inst in instruments}
    return {"candidate_footprints": k, "reference_footprints": m, "region": focus, "by_instrument": by}


# ------------------------------------------------------------------------------------ figures


def _figure(nrows=1, ncols=1, size=(9.0, 4.5), **kw):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def _shade_night(ax, days, night):
    if not night.any():
        return
    edges = np.flatnonzero(np.diff(np.r_[0, night.astype(int), 0]))
    for a, b in zip(edges[::2], edges[1::2]):
        ax.axvspan(days[a], days[min(b, len(days)) - 1], color="0.85", lw=0, zorder=0)


#: The time-series facets of a DEM site, in words (no floor or wall there).
_SITE_FACETS = {"floor": "facet nearest the centre", "upper_wall": "most sunlit facet"}


def _facet_title(A, key):
    i = A.facets[key]
    name = _SITE_FACETS.get(key, key) if is_site(A) else key.replace("_", " ")
    return f"{name} (facet {i}, {answer.region_words(A.region_label(i))})"


def _fig_fluxes(A, path):
    fig, ax = _figure(2, 1, (9, 6), sharex=True)
    for k, key in enumerate(("floor", "upper_wall")):
        i = A.facets[key]
        a = ax[k, 0]
        _shade_night(a, A.days, A.night)
        a.plot(
            A.days,
            A.run["solar_incident"].values[:, i],
            color="tab:orange",
            label="solar incident (direct + scattered)",
        )
        a.plot(A.days, A.run["ir_incident"].values[:, i], color="tab:red", label="IR emitted by the terrain, incident")
        a.set_ylabel("flux [W m-2]")
        a.set_title(_facet_title(A, key), fontsize=10)
        a.legend(fontsize=8, loc="upper right")
    centre = "the site centre" if is_site(A) else "the crater centre"
    ax[1, 0].set_xlabel(f"days since start (grey: night at {centre}; statistics use per-facet night)")
    fig.suptitle(f"Incident fluxes, lat {A.lat:g} deg")
    fig.savefig(path)


def _fig_temperature(A, path):
    fig, ax = _figure(2, 1, (9, 6), sharex=True)
    for k, key in enumerate(("floor", "upper_wall")):
        i = A.facets[key]
        a = ax[k, 0]
        _shade_night(a, A.days, A.night)
        a.plot(A.days, A.T_nom[:, i], color="k", label=f"nominal {A.nominal}")
        if A.loose:
            a.plot(A.days, A.profile_T(A.loose)[:, i], color="tab:blue", lw=0.8, label=f"loose {A.loose}")
        if A.rock:
            a.plot(A.days, A.profile_T(A.rock)[:, i], color="tab:brown", label=A.rock)
        a.set_ylabel("T [K]")
        a.set_title(_facet_title(A, key), fontsize=10)
        a.legend(fontsize=8, loc="upper right")
    ax[1, 0].set_xlabel("days since start (grey: night)")
    fig.suptitle(f"Surface temperature, lat {A.lat:g} deg")
    fig.savefig(path)


def _fig_dT_series(A, path):
    fig, ax = _figure(2, 1, (9, 6), sharex=True)
    for k, key in enumerate(("floor", "upper_wall")):
        i = A.facets[key]
        a = ax[k, 0]
        _shade_night(a, A.days, A.night)
        if A.loose:
            a.plot(A.days, A.loose_dT[:, i], color="tab:blue", label=f"{A.loose} - {A.nominal}")
        a.axhline(0, color="k", lw=0.5)
        for s in (-1, 1):
            a.axhline(s * an.NATURAL_SCATTER_K, color="tab:gray", ls=":", lw=0.8)
        a.set_ylabel("dT [K]")
        a.set_title(_facet_title(A, key) + "; dotted: +-0.94 K natural scatter", fontsize=10)
        a.legend(fontsize=8, loc="upper right")
    ax[1, 0].set_xlabel("days since start (grey: night)")
    fig.suptitle(f"Loose minus nominal, lat {A.lat:g} deg")
    fig.savefig(path)


def _fig_density_grid(A, path):
    from matplotlib.patches import Rectangle

    tops, bottoms, grid = A.density_grid()
    fig, ax = _figure(1, 1, (7, 5.5))
    a = ax[0, 0]
    m = np.nanmax(np.abs(grid)) if np.isfinite(grid).any() else 1.0
    m = m if m > 0 else 1.0
    im = a.imshow(np.ma.masked_invalid(grid), origin="lower", cmap="RdBu_r", vmin=-m, vmax=m, aspect="auto")
    a.set_xticks(range(bottoms.size), [f"{b:g}" for b in bottoms], rotation=45)
    a.set_yticks(range(tops.size), [f"{t:g}" for t in tops])
    a.set_xlabel("bottom-layer density [kg m-3]")
    a.set_ylabel("top-layer (2 cm) density [kg m-3]")
    a.set_facecolor("0.9")
    if grid.size <= 200:
        for (r, c), v in np.ndenumerate(grid):
            if np.isfinite(v):  # white on the dark ends of the colour map, black on the light middle
                a.text(c, r, f"{v:.2f}", ha="center", va="center", fontsize=7, color="w" if abs(v) > 0.6 * m else "k")
    nom = profiles.parse_two_layer(A.nominal)
    if nom and nom[0] in tops and nom[1] in bottoms:
        r, c = list(tops).index(nom[0]), list(bottoms).index(nom[1])
        a.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, fill=False, ec="k", lw=2.5))
    fig.colorbar(im, ax=a, label="night-time median, profile - nominal [K]")
    where = answer.region_words(A.grid_region) if A.grid_region else "all facets"
    a.set_title(f"{where[:1].upper() + where[1:]}, lat {A.lat:g} deg (nominal outlined)", fontsize=10)
    fig.savefig(path)


def _region_ticks(a, regions):
    a.set_xticks(
        range(len(regions)),
        [r.replace("_facing", "-facing").replace("_", " ") for r in regions],
        fontsize=7,
        rotation=45,
        ha="right",
        rotation_mode="anchor",
    )


def _aligned_regions(all_A) -> Tuple[List[str], List[List[Optional[str]]]]:
    """Region names of the first analysis and, per analysis, its name for each of them (None if absent).

    Regions of runs at different latitudes match by name, or by position when a polar run names its
    sectors by the Sun (``upper_wall_sun_facing`` beside ``upper_wall_equator_facing``)."""
    base = list(all_A[0].regions)
    per = []
    for B in all_A:
        names = list(B.regions)
        if names == base:
            per.append(list(base))
        elif len(names) == len(base):
            per.append(names)
        else:
            per.append([r if r in B.regions else None for r in base])
    return base, per


def _region_tick(base: str, others: Sequence[Optional[str]]) -> str:
    alt = sorted({o for o in others if o and o != base})
    return " ".join(
        [base.replace("_facing", "-facing").replace("_", " ")]
        + [f"({a.replace('_facing', '-facing').replace('_', ' ')})" for a in alt]
    )


def _fig_regions(all_A, path):
    base, per = _aligned_regions(all_A)
    keep = [
        j
        for j, r in enumerate(base)
        if any(p[j] and A.loose and A.night_stats[A.loose][p[j]]["n"] for A, p in zip(all_A, per))
    ]
    fig, ax = _figure(1, 1, (max(10.0, 0.75 * len(keep) + 2), 5.0))
    a = ax[0, 0]
    n = len(all_A)
    w = 0.8 / n
    x = np.arange(len(keep))
    for k, (A, names) in enumerate(zip(all_A, per)):
        if A.loose is None:
            continue
        st = A.night_stats[A.loose]
        q = np.array(
            [
                [
                    np.nan if names[j] is None or st[names[j]][key] is None else st[names[j]][key]
                    for key in ("q1_K", "median_K", "q3_K")
                ]
                for j in keep
            ]
        ).reshape(-1, 3)
        xs = x - 0.4 + w * (k + 0.5)
        a.bar(xs, q[:, 1], w, label=f"lat {A.lat:g} deg")
        a.errorbar(xs, q[:, 1], yerr=[q[:, 1] - q[:, 0], q[:, 2] - q[:, 1]], fmt="none", ecolor="k", lw=1)
    a.axhline(0, color="k", lw=0.5)
    a.set_xticks(
        x,
        [_region_tick(base[j], [p[j] for p in per]) for j in keep],
        fontsize=7,
        rotation=45,
        ha="right",
        rotation_mode="anchor",
    )
    a.set_ylabel("night-time median loose - nominal [K]")
    a.legend(fontsize=8)
    night = {
        "dark": "per facet: no sunlight, direct or scattered, for %g h" % all_A[0].min_dark_hours,
        "facet": "per facet: no direct sunlight for %g h" % all_A[0].min_dark_hours,
    }.get(all_A[0].night_definition, "Sun below the crater centre's horizon")
    a.set_title(
        f"By region (error bars: quartiles). Sectors: the azimuth the slope faces, +-45 deg; night {night}", fontsize=9
    )
    fig.savefig(path)


def _fig_night_map(all_A, path):
    from matplotlib.patches import Circle
    from matplotlib.tri import Triangulation

    n = len(all_A)
    fig, ax = _figure(1, n, (5.2 * n + 1.0, 5.0))
    maps = [np.abs(A.night_map[A.loose]) if A.loose else np.full(A.nf, np.nan) for A in all_A]
    vmax = max([float(np.nanmax(m)) for m in maps if np.isfinite(m).any()] + [1e-3])
    for k, A in enumerate(all_A):
        a = ax[0, k]
        v = np.asarray(A.run["mesh_vertices"].values, float) / 1000.0
        f = np.asarray(A.run["mesh_faces"].values, int)
        tri = Triangulation(v[:, 0], v[:, 1], f)
        pc = a.tripcolor(tri, facecolors=np.nan_to_num(maps[k], nan=0.0), cmap="magma", vmin=0, vmax=vmax)
        for key, ls in (("floor_radius_m", ":"), ("rim_radius_m", "--")):
            if self_r := A.meta.get(key):
                a.add_patch(Circle((0, 0), float(self_r) / 1000.0, fill=False, ec="w", ls=ls, lw=0.8))
        a.set_aspect("equal")
        a.set_xlabel("east [km]")
        a.set_ylabel("north [km]")
        a.set_title(f"lat {A.lat:g} deg (pole side: {'south' if A.lat <= 0 else 'north'})", fontsize=10)
    fig.colorbar(pc, ax=ax[0, :].tolist(), label="night-time median |loose - nominal| [K]")
    fig.savefig(path)


def _quart(st, r):
    s = st[r]
    return [np.nan if s[k] is None else s[k] for k in ("q1_K", "median_K", "q3_K")]


def _fig_quartiles(all_A, path):
    fig, ax = _figure(1, 2, (11, 4.5), sharey=True)
    if len(all_A) > 1:  # thesis Fig. 7.9: against latitude, one line per region
        lats = np.array([A.lat for A in all_A])
        order = np.argsort(lats)
        for j, when in enumerate(("night", "day")):
            a = ax[0, j]
            base, per = _aligned_regions(all_A)
            for r in ("floor", "upper_wall_equator_facing", "upper_wall_pole_facing"):
                if r not in base:
                    continue
                j = base.index(r)
                q = np.array(
                    [
                        _quart(getattr(all_A[i], f"{when}_stats")[all_A[i].loose], per[i][j])
                        if per[i][j]
                        else [np.nan] * 3
                        for i in order
                    ]
                )
                (line,) = a.plot(lats[order], q[:, 1], marker="o", label=f"{r} median")
                a.fill_between(lats[order], q[:, 0], q[:, 2], color=line.get_color(), alpha=0.2)
            a.set_xlabel("latitude [deg]")
            a.set_title(f"{when}: median, band = 1st-3rd quartile", fontsize=10)
            a.legend(fontsize=7)
    else:
        A = all_A[0]
        x = np.arange(len(A.regions))
        for j, when in enumerate(("night", "day")):
            a = ax[0, j]
            if A.loose:
                q = np.array([_quart(getattr(A, f"{when}_stats")[A.loose], r) for r in A.regions])
                a.errorbar(
                    x,
                    q[:, 1],
                    yerr=[q[:, 1] - q[:, 0], q[:, 2] - q[:, 1]],
                    fmt="o",
                    capsize=4,
                    color="tab:blue" if when == "night" else "tab:orange",
                )
            a.axhline(0, color="k", lw=0.5)
            _region_ticks(a, list(A.regions))
            a.set_title(f"{when} (lat {A.lat:g} deg): median and quartiles", fontsize=10)
    ax[0, 0].set_ylabel("loose - nominal [K]")
    fig.savefig(path)


def _region_style(region: str, regions) -> dict:
    """A distinct colour (20-colour cycle) and, past 20 regions, a line style for one of many regions."""
    from matplotlib import colormaps

    k = list(regions).index(region)
    return {"color": colormaps["tab20"](k % 20), "ls": ("-", "--", ":")[(k // 20) % 3]}


def _fig_detectability(summary: dict, path):
    det, grids, obs = summary["detection"], summary["detection_dwell_grid_s"], summary["observation"]
    names = list(det)
    ncol = min(2, max(1, len(names)))
    nrow = max(1, math.ceil(len(names) / ncol))
    fig, ax = _figure(nrow, ncol, (6.0 * ncol, 3.6 * nrow), sharey=True)
    for k, name in enumerate(names):
        a = ax[k // ncol, k % ncol]
        x = np.asarray(grids[name], float)
        t_pass = (obs.get("pass_integration_s_by_instrument") or {}).get(name)
        if t_pass is not None:  # pass mode: the grid is whole passes x time per pass
            x = x / t_pass
        for r, row in det[name].items():
            if row.get("pd_vs_dwell") is None:
                continue
            a.plot(x, row["pd_vs_dwell"], lw=1.2, label=answer.region_words(r), **_region_style(r, det[name]))
        a.axhline(obs["target_pd"], color="k", ls="--", lw=0.8)
        a.axhline(obs["false_alarm"], color="0.5", ls=":", lw=0.8)
        a.set_xscale("log")
        a.set_ylim(0, 1)
        inst = summary["instruments"][name]
        a.set_title(f"{name} ({inst['lo_um']:g}-{inst['hi_um']:g} um)", fontsize=9)
        a.set_xlabel(
            f"orbital passes ({t_pass:.3g} s on each footprint per pass)"
            if t_pass is not None
            else "dwell on each footprint (stare) [s]"
        )
        a.set_ylabel("P_D")
    for k in range(len(names), nrow * ncol):
        ax[k // ncol, k % ncol].set_visible(False)
    ax[0, ax.shape[1] - 1].legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # outside the data
    fig.suptitle(
        f"Lat {summary['lat_deg']:g} deg, loose vs nominal, night medians: one-sided test at "
        f"{100 * obs['false_alarm']:g}% false alarms "
        f"(dotted); dashed: P_D = {obs['target_pd']:g}; natural scatter {obs['natural_scatter_K']:g} K, "
        f"{obs.get('candidate_footprints', 1)} candidate vs {obs['reference_footprints']} reference footprint(s)",
        fontsize=9,
    )
    fig.savefig(path)


def _best_instrument(summary: dict) -> Optional[str]:
    """The instrument with the shortest floor dwell (or the highest P_D limit) for the report's time plot."""
    det = summary["detection"]

    def key(name):
        row = det[name].get("floor") or next(iter(det[name].values()), {})
        d = row.get("dwell_s")
        return (0, d) if d is not None else (1, -(row.get("pd_limit") or 0.0))

    return min(det, key=key) if det else None


def _fig_detectability_scatter(summary: dict, path) -> None:
    sweep, obs = summary["detectability_vs_scatter"], summary["observation"]
    x = np.asarray(sweep["scatter_K"], float)
    fig, ax = _figure(1, 1, (7.0, 4.2))
    a = ax[0, 0]
    from matplotlib import colormaps

    colors = colormaps["tab10"]
    for k, (name, secs) in enumerate(sweep["dwell_s"].items()):
        y = np.array([np.nan if v is None else v for v in secs], float)
        unit = sweep["exposure_unit"][name]
        a.plot(
            x,
            y,
            "o-",
            ms=3,
            lw=1.3,
            color=colors(k % 10),
            label=f"{name} ({'passes' if unit == 'passes' else 'stare'})",
        )
    a.axvline(obs["natural_scatter_K"], color="k", ls="--", lw=0.8)
    seen = [v for secs in sweep["dwell_s"].values() for v in secs if v is not None]
    if seen:
        a.set_yscale("log")
    else:  # nothing is detectable at any scatter of the range: say so instead of an empty log axis
        a.set_ylim(0, 1)
        a.text(0.5, 0.5, "not detectable at any scatter in this range", ha="center", va="center", transform=a.transAxes)
    a.set_xlabel("natural scatter between footprints [K]")
    a.set_ylabel(f"time on each footprint for P_D >= {obs['target_pd']:g} [s]")
    a.set_title(
        f"{answer.region_words(sweep['region'])}: {obs.get('candidate_footprints', 1)} loose vs "
        f"{obs['reference_footprints']} reference footprints, {100 * obs['false_alarm']:g}% false alarms",
        fontsize=9,
    )
    a.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    a.grid(True, which="both", alpha=0.3)
    fig.savefig(path, dpi=110)


def _fig_local_time(summary: dict, path):
    name = _best_instrument(summary)
    obs = summary["observation"]
    fig, ax = _figure(1, 1, (9, 4.2))
    a = ax[0, 0]
    if name is not None:
        centres = (np.arange(_LT_BINS) + 0.5) * 24.0 / _LT_BINS
        for r, row in summary["detection"][name].items():
            snr = row.get("snr_by_local_time")
            if snr is None:
                continue
            a.plot(
                centres,
                [np.nan if v is None else v for v in snr],
                marker=".",
                lw=1,
                label=answer.region_words(r),
                **_region_style(r, summary["detection"][name]),
            )
        a.axhline(
            float(ins.ndtri(1 - obs["false_alarm"]) + ins.ndtri(obs["target_pd"])),
            color="k",
            ls="--",
            lw=0.8,
            label=f"needed for P_D {obs['target_pd']:g} (no gain error)",
        )
        at = f"{summary['detection_reference_dwell_s']:g} s dwell"
        if (obs.get("mode_by_instrument") or {}).get(name) == "passes":
            at = f"{obs['passes']} passes"
        a.set_title(
            f"{name}: |observed dT| / sigma at {at}, by local solar time (lat {summary['lat_deg']:g} deg)",
            fontsize=9,
        )
        a.legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.02, 1.0))  # outside the data
    a.set_xlim(0, 24)
    a.set_xticks(range(0, 25, 3))
    a.set_xlabel("local solar time [lunar hours; 12 = noon]")
    a.set_ylabel("|dT| / sigma")
    fig.savefig(path)


# ------------------------------------------------------------------------- DEM sites: plan-view maps

#: Figure of a DEM site (kind "dem"): maps in the DEM's own projected coordinates.
SITE_FIGURES = {
    "site_maps.png": "Plan view in the DEM's projected coordinates (x, y [km]): per-facet night-time median nominal "
    "temperature, night-time median loose minus nominal, and the probability of detecting it at the "
    "reference dwell (best instrument); outer shadow-only terrain grey.",
}


def is_site(A) -> bool:
    """True for a run on a DEM site (mesh kind "dem"): crater radii do not exist there."""
    return A.meta.get("kind") == "dem"


def _night_facet_median(values: np.ndarray, night) -> np.ndarray:
    """(nf,) per-facet median over the night samples [same unit]; ``night`` (nt,) or (nt, nf) bool."""
    mask = np.asarray(night, bool)
    if mask.ndim == 1:
        return np.median(values[mask], axis=0) if mask.any() else np.full(values.shape[1], np.nan)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # facets without a night sample: NaN
            return np.nanmedian(np.where(mask, values, np.nan), axis=0)


def site_plan_coordinates(run) -> Tuple[np.ndarray, str]:
    """(nv, 2) vertex positions [km] in the DEM's projected CRS, and the CRS name (terrain does the projection)."""
    from crater_thermal import terrain

    meta = ctio.mesh_meta(run)
    x, y = terrain.local_to_dem_xy(np.asarray(run["mesh_vertices"].values, float), meta)
    return np.column_stack([np.asarray(x), np.asarray(y)]) / 1000.0, str(meta.get("crs_name", "DEM CRS"))


def _fig_site_maps(A, path, instruments: Sequence[ins.Instrument], observation: ins.Observation) -> None:
    from matplotlib.tri import Triangulation

    xy, crs_name = site_plan_coordinates(A.run)
    f = np.asarray(A.run["mesh_faces"].values, int)
    inner = np.asarray(A.run["inner"].values, bool) if "inner" in A.run else np.ones(len(f), bool)
    tri = Triangulation(xy[:, 0], xy[:, 1], f)
    night = getattr(A, "night_f", A.night)  # per-facet night where the analysis has it
    T_night = _night_facet_median(A.T_nom, night)
    panels = [(T_night, "night-time median T, nominal [K]", "inferno", None)]
    if A.loose is not None:
        dT = _night_facet_median(A.loose_dT, night) if A.loose_dT is not None else A.night_map[A.loose]
        lim = float(np.nanmax(np.abs(dT[inner]))) if np.isfinite(dT[inner]).any() else 1.0
        panels.append((dT, f"night-time median {A.loose} - nominal [K]", "RdBu_r", (-max(lim, 1e-3), max(lim, 1e-3))))
        if instruments:
            inst = instruments[0]
            ok = np.isfinite(dT) & np.isfinite(T_night) & (T_night + np.nan_to_num(dT) > 0)
            pd = np.full(len(f), np.nan)
            expo = ins.stated_exposure(inst, observation, REFERENCE_DWELL_S)
            k = np.flatnonzero(ok & inner)
            pd[k] = ins.detection_probability(dT[k], T_night[k], expo, inst, observation)  # all facets at once
            at = f"{expo:.0f} passes" if ins.observing_mode(inst, observation) == "passes" else f"{expo:g} s"
            panels.append((pd, f"P(detect) in {at}, {inst.name}", "viridis", (0.0, 1.0)))
    n = len(panels)
    fig, ax = _figure(1, n, (5.0 * n + 0.6, 4.9))
    for k, (vals, label, cmap, clim) in enumerate(panels):
        a = ax[0, k]
        v = np.array(vals, float)
        v[~inner] = np.nan
        if not inner.all():  # outer shadow-only terrain, light grey
            from matplotlib.colors import ListedColormap

            a.tripcolor(tri, facecolors=np.zeros(len(f)), cmap=ListedColormap(["#d9d9d9"]))
        tri_in = Triangulation(xy[:, 0], xy[:, 1], f[inner])
        lo, hi = clim if clim else (float(np.nanmin(v)), float(np.nanmax(v)))
        pc = a.tripcolor(
            tri_in, facecolors=np.nan_to_num(v[inner], nan=lo), cmap=cmap, vmin=lo, vmax=max(hi, lo + 1e-3)
        )
        fig.colorbar(pc, ax=a, shrink=0.8, label=label)
        a.set_aspect("equal")
        a.set_xlabel("x [km]")
        a.set_ylabel("y [km]")
        a.set_title(label.split(" [")[0], fontsize=9)
    fig.suptitle(
        f"{A.meta.get('dem_source', 'DEM')} ({crs_name}), centre {A.lat:g} deg, "
        f"{float(A.run.attrs.get('lon_deg', np.nan)):g} deg",
        fontsize=10,
    )
    fig.savefig(path)


def site_summary(A) -> Optional[dict]:
    """The DEM site of a run (summary.json ``site``), or None for an idealized crater / mesh file."""
    if not is_site(A):
        return None
    m = A.meta
    inner = np.asarray(A.run["inner"].values, bool) if "inner" in A.run else np.ones(A.run.sizes["facet"], bool)
    keys = (
        "dem_source",
        "crs_name",
        "center_lat_deg",
        "center_lon_deg",
        "reference_radius_m",
        "radius_km",
        "resolution_m",
        "outer_radius_km",
        "outer_resolution_m",
        "height_kind",
        "dem_pixel_m",
    )
    out = {k: m.get(k) for k in keys}
    out.update(n_inner=int(inner.sum()), n_outer=int((~inner).sum()))
    return out


def _html_site(site: dict) -> str:
    """One paragraph describing a DEM site (replaces the crater-region explanation)."""
    ring = (
        f"; outer ring to {site['outer_radius_km']:g} km at {site['outer_resolution_m']:.4g} m "
        f"({site['n_outer']} facets: shadows and radiation only, not analysed)"
        if site.get("outer_radius_km")
        else ""
    )
    return (
        f"<p><b>Site</b> from the DEM <code>{html.escape(str(site['dem_source']))}</code> "
        f"({html.escape(str(site['crs_name']))}, {site['dem_pixel_m']:.3g} m pixels, values read as "
        f"{html.escape(str(site['height_kind']))}): centre {site['center_lat_deg']:g} deg, "
        f"{site['center_lon_deg']:g} deg; analysed disk of {site['radius_km']:g} km at "
        f"{site['resolution_m']:.4g} m ({site['n_inner']} facets){ring}. Vertices are true 3-D positions in the "
        "centre's east/north/up frame (curvature included). Regions are classes by illumination over the run, "
        "by slope and by the direction the slope faces; the maps are in the DEM's projected coordinates.</p>"
    )


def _snapshots(A: _Analysis, fig_dir: Path) -> List[str]:
    from crater_thermal import viz

    i = int(np.argmax(np.asarray(A.run["sun_direction"].values)[:, 2]))
    vx = viz.site_exaggeration(A.run)
    viz.snapshot(
        A.run,
        A.T_nom[i],
        i,
        "Surface temperature [K]",
        f"Nominal {A.nominal}",
        fig_dir / "map3d_temperature.png",
        cmap="inferno",
        exaggeration=vx,
    )
    out = ["map3d_temperature.png"]
    if A.loose is not None:
        m = A.night_map[A.loose]
        lim = float(np.nanmax(np.abs(m))) if np.isfinite(m).any() else 1.0
        j = int(np.flatnonzero(A.night)[0]) if A.night.any() else i
        viz.snapshot(
            A.run,
            m,
            j,
            "night median dT [K]",
            f"Night-time median {A.loose} - nominal",
            fig_dir / "map3d_night_dT.png",
            cmap="RdBu_r",
            clim=(-max(lim, 1e-3), max(lim, 1e-3)),
            exaggeration=vx,
        )
        out.append("map3d_night_dT.png")
    return out


# --------------------------------------------------------------------------------------- HTML


def _table(rows: List[List[str]], header: List[str], markup_first: bool = False) -> str:
    """An HTML table of text cells (escaped; with ``markup_first`` the first column is HTML already)."""
    h = "".join(f"<th>{html.escape(c)}</th>" for c in header)
    body = "".join(
        "<tr>"
        + "".join(f"<td>{c if (markup_first and j == 0) else html.escape(c)}</td>" for j, c in enumerate(r))
        + "</tr>"
        for r in rows
    )
    return f"<table><tr>{h}</tr>{body}</table>"


def _fmt(v, spec=".2f"):
    return "-" if v is None else format(v, spec)


def _exposure_text(seconds, t_pass) -> str:
    """A total time on each footprint [s] as the mode states it: "52 passes (6.66 s)" or "6.66 s"."""
    if seconds is None:
        return "-"
    if t_pass is None:
        return f"{seconds:.3g} s"
    P = round(seconds / t_pass)
    return f"{P} {'pass' if P == 1 else 'passes'} ({seconds:.3g} s)"


def _html_detection(summary: dict) -> str:
    """The detectability section: which bands see the difference, and per instrument and region the answer."""
    obs = summary["observation"]
    t_passes = obs.get("pass_integration_s_by_instrument") or {}
    modes = [
        f"{n}: {t:.3g} s on each footprint per orbital pass" if t is not None else f"{n}: stare (dwell [s])"
        for n, t in t_passes.items()
    ]
    parts = [
        "<h2>Can an instrument tell loose from nominal regolith?</h2>",
        f"<p>Candidate patch of {obs.get('candidate_footprints', 1)} footprint(s) "
        f"({100 * obs['footprint_fraction']:g}% loose each, mixed with nominal in band radiance) against "
        f"{obs['reference_footprints']} nominal reference footprint(s), each observed alike. Observation: "
        f"{html.escape('; '.join(modes) or 'stare')}. Noise terms: instrument NETD(T) (scaled with the band's "
        f"dB/dT) averaged over the samples down to a 1/f floor (per pass with passes), in both scenes; natural "
        f"scatter {obs['natural_scatter_K']:g} K per footprint (measured by Diviner on night-time regolith "
        f"between 60 N and 60 S, about 80-120 K; uncertain by a factor ~2 at 40-80 K); calibration gain error on "
        f"band radiances (its effect on the temperature difference is g &middot; dT &middot; d(L/L')/dT). Test: "
        f"{html.escape(obs['test'])} (every footprint nominal), false-alarm rate {100 * obs['false_alarm']:g}%; "
        f"the exposure (dwell or passes) is the shortest with P_D &ge; {obs['target_pd']:g}. Night-time medians "
        f"of loose minus nominal.</p>",
    ]
    sees, blind = [], []
    for name, per in summary["detection"].items():
        row = per.get("floor") or next((v for v in per.values() if v.get("dT_median_K") is not None), {})
        if row.get("dT_median_K") is None:
            continue
        if row.get("dwell_s_no_scatter") is not None:
            sees.append(
                f"{name} (instrument noise alone: {_exposure_text(row['dwell_s_no_scatter'], t_passes.get(name))})"
            )
        else:
            blind.append(f"{name} (NETD {row['netd_candidate_K']:.3g} K at {row['T_candidate_K']:.1f} K)")
    parts.append(
        "<p><b>Bands that can see the night-time difference on the floor</b> (ignoring natural scatter): "
        f"{html.escape(', '.join(sees) or 'none')}. <b>Bands that cannot</b>: "
        f"{html.escape(', '.join(blind) or 'none')}.</p>"
    )
    band = summary["band_signal_night_floor"]
    rows = []
    for name, b in band.items():
        for T, L, e in zip(b["T_K"], b["band_radiance_W_m2_sr"], b["netd_K"]):
            rows.append([name, f"{b['band_um'][0]:g}-{b['band_um'][1]:g}", f"{T:.1f}", f"{L:.3g}", f"{e:.3g}"])
    parts.append("<h3>What each band receives (night floor, nominal; and a 300 K scene)</h3>")
    parts.append(
        _table(rows, ["instrument", "band [um]", "T [K]", "band radiance [W m-2 sr-1]", "NETD of one integration [K]"])
    )
    for name, per in summary["detection"].items():
        inst = summary["instruments"][name]
        t_pass = t_passes.get(name)
        rows = []
        for r, d in per.items():
            lt = d.get("best_local_time_h")
            rows.append(
                [
                    r,
                    _fmt(d.get("dT_median_K")),
                    f"{_fmt(d.get('dT_q1_K'))} .. {_fmt(d.get('dT_q3_K'))}",
                    _fmt(d.get("T_nominal_K"), ".1f"),
                    _fmt(d.get("netd_candidate_K"), ".3g"),
                    _exposure_text(d.get("dwell_s"), t_pass) if d.get("detectable") else "never",
                    _fmt(d.get("pd_limit")),
                    str(d.get("limiting_term") or "-").replace("_", " "),
                    "-" if lt is None else f"{lt:.1f} h (|dT|/sigma {d['best_snr']:.2g})",
                    f"{_exposure_text(d.get('dwell_s_scatter_half'), t_pass)} / "
                    f"{_exposure_text(d.get('dwell_s_scatter_double'), t_pass)}",
                    d.get("answer", ""),
                ]
            )
        parts.append(
            f"<h3>{html.escape(name)}: {inst['lo_um']:g}-{inst['hi_um']:g} um, NETD "
            f"{inst['netd_ref_K']:.3g} K at {inst['t_ref_K']:g} K per {inst['integration_s']:.3g} s, "
            f"1/f knee {inst['knee_s']:g} s, gain error {100 * inst['gain_error']:g}%; "
            + (f"orbital passes of {t_pass:.3g} s on each footprint" if t_pass is not None else "stare")
            + "</h3>"
            f"<p><small>{html.escape(inst['source'])}</small></p>"
        )
        parts.append(
            _table(
                rows,
                [
                    "region",
                    "night median dT [K]",
                    "quartiles [K]",
                    "T nominal [K]",
                    "NETD at candidate [K]",
                    "passes for P_D (time on footprint)" if t_pass is not None else "dwell for P_D [s]",
                    "P_D at infinite exposure",
                    "limiting term",
                    "best local time",
                    "passes with scatter x0.5 / x2" if t_pass is not None else "dwell with scatter x0.5 / x2 [s]",
                    "answer",
                ],
            )
        )
    return "\n".join(parts)


def _night_words(summary: dict) -> str:
    """What "night" means in this report, from summary.json."""
    if summary["night_definition"] == "dark":
        n_fb = summary.get("night_fallback_facets") or 0
        fb = (
            f"; {n_fb} facets never dark that long use their "
            f"{100 * summary['night_fallback_fraction']:g}% least-lit samples without direct sunlight instead"
            if n_fb
            else ""
        )
        return (
            f"night = no sunlight, direct or scattered (at most {summary['night_threshold_W_m2']:g} W m-2), on the "
            f"facet for at least {summary['night_min_dark_hours']:g} h{fb}; day = the facet receives sunlight"
        )
    if summary["night_definition"] == "facet":
        return (
            f"night = no direct sunlight on the facet for at least {summary['night_min_dark_hours']:g} h, day = "
            "the facet directly lit (a never-lit facet has no day)"
        )
    if summary["night_definition"] == "centre":
        return "night = Sun's centre below the horizon at the crater centre (thesis)"
    return f"night definition {html.escape(str(summary['night_definition']))} (see summary.json)"


def _figure_html(name: str, fig_dir: Path, caption: str) -> str:
    data = base64.b64encode((fig_dir / name).read_bytes()).decode("ascii")
    return (
        f"<figure><img alt='figures/{name}' src='data:image/png;base64,{data}'>"
        f"<figcaption><a href='figures/{name}'>figures/{name}</a>: {html.escape(caption)}</figcaption></figure>"
    )


#: The figure beside the headline: the plan-view map of the night contrast (a DEM site: its site maps).
KEY_FIGURES = ("fig7_8_night_map.png", "site_maps.png")


def _html(summary: dict, fig_dir: Path, captions: Dict[str, str]) -> str:
    """report.html: the answer and its key figure on the first screen, then the figures, then the tables
    (collapsed), a glossary and the summary.json keys."""
    key = next((n for n in KEY_FIGURES if n in summary["figures"]), None)
    about = (
        f"{summary['time_start_utc']} to {summary['time_end_utc']}, {summary['n_times']} samples, "
        f"{summary['n_facets']} facets (mesh {html.escape(summary['mesh_hash'])}); night fraction "
        f"{summary['night_fraction']:.2f}. Differences are replayed profile minus nominal "
        f"({html.escape(summary['nominal_profile'])}); "
        + _night_words(summary)
        + f" ({summary['night_fraction_samples']:.2f} of the samples are night). "
        + (
            "Regions: classes by slope, by the azimuth the slope faces (+-45 deg sectors; <i>level</i> below 5 deg) "
            "and by direct sunlight (never / rarely (&lt; 10% of samples) / often lit), over the analysed facets "
            "only. Regions may overlap."
            if summary.get("site")
            else "Regions: floor; lower/upper wall (below/above half the wall's height); top wall ring (the facets at "
            "the crest); rim (outer flank); surround; each wall/rim part split into +-45 deg sectors by the "
            "azimuth its slope faces (<i>equator_facing</i>: on the pole side, facing the equator and the Sun); "
            "never / rarely (&lt; 10% of samples) / often lit by direct sunlight. Regions may overlap."
        )
    )
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>crater_thermal report</title>",
        "<style>body{font-family:sans-serif;max-width:1200px;margin:auto;padding:0.6em 1em}"
        "h1{font-size:1.35em;margin:0.2em 0 0.4em}img{max-width:100%;border:1px solid #ccc}"
        "table{border-collapse:collapse;font-size:90%}td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}"
        "td:first-child{text-align:left}figure{margin:1.2em 0}.answer{display:flex;gap:1.2em;align-items:flex-start;"
        "flex-wrap:wrap}.answer .text{flex:1 1 380px}.answer figure{flex:1 1 480px;margin:0}"
        ".headline{font-size:1.08em;line-height:1.45}.about{font-size:85%;color:#444}"
        "details{margin:0.8em 0}summary{cursor:pointer;font-weight:bold}</style></head><body>",
        f"<h1>Loose vs compact regolith at night: lat {summary['lat_deg']:g} deg, lon {summary['lon_deg']:g} deg</h1>",
        "<div class='answer' id='answer'><div class='text'>",
        f"<p class='headline' id='headline'>{html.escape(summary['headline'])}</p>",
        f"<p class='about'>{about}</p>",
        "</div>",
        _figure_html(key, fig_dir, captions.get(key, "")) if key else "",
        "</div>",
    ]
    if summary["snapshot_note"]:
        parts.append(f"<p><b>Note:</b> {html.escape(summary['snapshot_note'])}</p>")
    parts.append("<h2>Figures</h2>")
    for name in summary["figures"]:
        if name != key:
            parts.append(_figure_html(name, fig_dir, captions.get(name, "")))
    loose = summary["loose_profile"]
    tables = []
    if summary.get("site"):  # a DEM site: say what was meshed (no crater radii here)
        tables.append(_html_site(summary["site"]))
    if loose:
        rows = []
        for r in summary["regions"]:
            rows.append(
                [
                    f"<span title='{html.escape(r)}'>{html.escape(answer.region_words(r))}</span>",
                    str(summary["region_facet_count"][r]),
                    _fmt(summary["night_median_T_nominal_K"][r], ".1f"),
                    _fmt(summary["night_median_dT_K"][loose][r]),
                    f"{_fmt(summary['night_q1_dT_K'][loose][r])} .. {_fmt(summary['night_q3_dT_K'][loose][r])}",
                    _fmt(summary["day_median_dT_K"][loose][r]),
                    _fmt(summary["night_frac_abs_dT_above_threshold"][loose][r]),
                ]
            )
        tables.append(f"<h3>{html.escape(loose)} minus nominal by region</h3>")
        tables.append(
            _table(
                rows,
                [
                    "region",
                    "facets",
                    "night T nominal [K]",
                    "night median dT [K]",
                    "night quartiles [K]",
                    "day median dT [K]",
                    f"night frac |dT|>{summary['threshold_K']:g} K",
                ],
                markup_first=True,
            )
        )
        tables.append(_html_detection(summary))
    if tables:
        parts.append("<details id='tables'><summary>Tables: regions and detection statistics</summary>")
        parts.extend(tables)
        parts.append("</details>")
    parts.append(
        "<details id='glossary'><summary>Glossary</summary><dl>"
        + "".join(f"<dt>{html.escape(k)}</dt><dd>{html.escape(v)}</dd>" for k, v in answer.GLOSSARY.items())
        + "</dl></details>"
    )
    parts.append(
        "<details><summary>summary.json keys</summary><dl>"
        + "".join(f"<dt><code>{html.escape(k)}</code></dt><dd>{html.escape(v)}</dd>" for k, v in SUMMARY_KEYS.items())
        + "</dl></details>"
    )
    parts.append("</body></html>")
    return "\n".join(parts)


# ----------------------------------------------------------------------------------- make_report


def _as_list(x) -> list:
    return list(x) if isinstance(x, (list, tuple)) else [x]


#: What a report writes into its folder (anything else there is left alone).
_MEMBERS = ("report.html", "summary.json", "figures")


def _refuse_existing(out_dir: Path, overwrite: bool, inputs=()) -> None:
    """Refuse an existing report (any of :data:`_MEMBERS`) unless ``overwrite``, or one that would replace
    one of the ``inputs`` (even with ``overwrite``), before any work."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"report folder {out_dir} is a file; give a folder name")
    for name in _MEMBERS:
        ctio.check_output(out_dir / name, overwrite, folder=name == "figures", inputs=inputs)


def sweep_pairs(folder) -> Tuple[List[Path], List[Path]]:
    """``(runs, replays)`` of a sweep's output folder (``FOLDER/CASE/run.nc`` + ``replay.nc``, see sweep.py).

    Cases without a replay are skipped; sorted by case name. Raises :class:`ConfigError` when none is found.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(
            f"{folder} is not a folder; expected a sweep output folder with CASE/run.nc and CASE/replay.nc"
        )
    cases = sorted(d for d in folder.iterdir() if (d / "run.nc").is_file() and (d / "replay.nc").is_file())
    if not cases:
        raise ConfigError(f"{folder} holds no CASE/run.nc with CASE/replay.nc (a sweep's output folder)")
    return [d / "run.nc" for d in cases], [d / "replay.nc" for d in cases]


def make_report(
    run_ds,
    replay_ds,
    out_dir,
    overwrite: bool = False,
    progress: Optional[bool] = None,
    instruments: Optional[Sequence[ins.Instrument]] = None,
    observation: ins.Observation = ins.Observation(),
    threshold_K: float = an.NATURAL_SCATTER_K,
    snapshots: bool = True,
    night_definition: str = regions.DEFAULT_NIGHT,
    min_dark_hours: float = regions.MIN_DARK_HOURS,
) -> Path:
    """Write figures, report.html and summary.json for a run and its replay.

    Parameters
    ----------
    run_ds, replay_ds : dataset or path, or equal-length sequences of them (one pair per latitude;
        the first pair drives the single-crater figures, all pairs the latitude comparisons).
        With ``replay_ds=None``, ``run_ds`` is a sweep's output folder (:func:`sweep_pairs`).
    out_dir : path
        Output folder (created).
    overwrite : bool
        Replace an existing ``out_dir/report.html``.
    progress : bool, optional
        Rich progress bar on stderr; default only when stderr is a terminal.
    instruments : sequence of instrument.Instrument, optional
        Channels for the detection statistics (default: every preset, ``instrument.PRESETS``).
    observation : instrument.Observation
        Footprint fraction, reference footprints, natural scatter, false-alarm rate, target P_D.
    threshold_K : float [K]
        |dT| threshold for the fraction-above statistic (default the 0.94 K natural scatter).
    snapshots : bool
        Also render 3-D views with pyvista (a note replaces them if rendering fails).
    night_definition : str
        "dark" (default: no sunlight, direct or scattered, on the facet for ``min_dark_hours``, with the
        least-lit fallback), "facet" (no direct sunlight), "centre" (the thesis: Sun below the crater
        centre's horizon) or "facet_and_centre" (regions.night_selection).
    min_dark_hours : float [h]
        Darkness a facet needs before its samples count as night (24 h).

    Returns
    -------
    Path of ``report.html``.

    Raises
    ------
    FluxFileError
        The replay does not belong to the run (mesh hash, time axis) or variables are missing.
    OutputExistsError
        ``out_dir/report.html`` exists and ``overwrite`` is False.
    """
    out_dir = Path(out_dir)
    inputs = [p for p in _as_list(run_ds) + _as_list(replay_ds) if isinstance(p, (str, os.PathLike))]
    _refuse_existing(out_dir, overwrite, inputs)
    with _report_folder(out_dir):
        instruments = list(ins.PRESETS.values()) if instruments is None else list(instruments)
        if not instruments:
            raise ConfigError("need at least one instrument")
        if replay_ds is None:
            run_ds, replay_ds = sweep_pairs(run_ds)
        if night_definition not in regions.NIGHT_DEFINITIONS:
            raise ConfigError(
                f"night definition {night_definition!r} not one of {', '.join(regions.NIGHT_DEFINITIONS)}"
            )
        if not (np.isfinite(min_dark_hours) and min_dark_hours >= 0):
            raise ConfigError(f"min_dark_hours={min_dark_hours} out of range [0, inf)")
        runs, reps = _as_list(run_ds), _as_list(replay_ds)
        if len(runs) != len(reps) or not runs:
            raise ConfigError(f"need one replay per run, got {len(runs)} runs and {len(reps)} replays")
        opened = []
        try:
            runs = [_track(ctio.open_run(r), opened) if isinstance(r, (str, os.PathLike)) else r for r in runs]
            reps = [_track(ctio.open_replay(r), opened) if isinstance(r, (str, os.PathLike)) else r for r in reps]
            return _make_report(
                runs,
                reps,
                out_dir,
                overwrite,
                progress,
                instruments,
                threshold_K,
                observation,
                snapshots,
                night_definition,
                min_dark_hours,
            )
        finally:
            for ds in opened:
                ds.close()


@contextlib.contextmanager
def _report_folder(out_dir: Path):
    """Hold the report folder's lock; a failed or interrupted report leaves no empty folder it created."""
    created = not out_dir.exists()
    try:
        with ctio.output_lock(out_dir):
            yield
    except BaseException:
        if created and out_dir.is_dir() and not any(out_dir.iterdir()):
            out_dir.rmdir()
        raise


def summarize(
    run_ds,
    replay_ds,
    instruments: Optional[Sequence[ins.Instrument]] = None,
    observation: ins.Observation = ins.Observation(),
    threshold_K: float = an.NATURAL_SCATTER_K,
    night_definition: str = regions.DEFAULT_NIGHT,
    min_dark_hours: float = regions.MIN_DARK_HOURS,
) -> dict:
    """The numbers of a report (``summary.json``) for one run and its replay, without figures or files.

    ``run_ds``, ``replay_ds``: datasets or paths. Returns the summary dictionary (temperatures [K],
    differences [K], dwell times [s], as in ``summary.json``; ``figures`` is empty).
    """
    instruments = list(ins.PRESETS.values()) if instruments is None else list(instruments)
    if not instruments:
        raise ConfigError("need at least one instrument")
    if night_definition not in regions.NIGHT_DEFINITIONS:
        raise ConfigError(f"night definition {night_definition!r} not one of {', '.join(regions.NIGHT_DEFINITIONS)}")
    opened = []
    try:
        run = _track(ctio.open_run(run_ds), opened) if isinstance(run_ds, (str, os.PathLike)) else run_ds
        rep = _track(ctio.open_replay(replay_ds), opened) if isinstance(replay_ds, (str, os.PathLike)) else replay_ds
        ctio.check_run(run, ctio.RUN_VARIABLES + ("solar_incident", "ir_incident"))
        A = _Analysis(run, rep, threshold_K, night_definition=night_definition, min_dark_hours=min_dark_hours)
        return _summary(A, [], instruments, observation, [], None)
    finally:
        for ds in opened:
            ds.close()


def _track(ds, opened: list):
    opened.append(ds)
    return ds


def _make_report(
    runs,
    reps,
    out_dir: Path,
    overwrite,
    progress,
    instruments,
    threshold_K,
    observation,
    snapshots,
    night_definition=regions.DEFAULT_NIGHT,
    min_dark_hours=regions.MIN_DARK_HOURS,
) -> Path:
    for run, rep in zip(runs, reps):
        ctio.check_run(run, ctio.RUN_VARIABLES + ("solar_incident", "ir_incident"))
        ctio.check_pair(run, rep)
    n_profiles = sum(len(an.profile_labels(p)) - 1 for p in reps)
    n_steps = n_profiles + len(FIGURES) + 1
    with bar("report: profiles, figures", progress) as report:
        done = [0]

        def advance() -> None:
            done[0] += 1
            if report is not None:
                report(done[0], n_steps)

        all_A = [_Analysis(r, p, threshold_K, advance, night_definition, min_dark_hours) for r, p in zip(runs, reps)]
        return _write_report(all_A, out_dir, overwrite, advance, instruments, observation, snapshots)


def _figures_without_data(A) -> set:
    """The figures a run and replay have nothing to draw in: no loose profile (a rock-only or single-profile
    replay), or no density grid (fewer than three replayed two-layer profiles)."""
    skip = set()
    if A.loose is None:  # the figures of loose - nominal
        skip |= {
            "fig7_6_loose_minus_nominal.png",
            "fig7_7b_regions.png",
            "fig7_8_night_map.png",
            "fig7_9_quartiles.png",
        }
    _, _, grid = A.density_grid()
    cells = [v for row in grid for v in row if v is not None and np.isfinite(v)] if grid is not None else []
    if len(cells) < 3:
        skip.add("fig7_7a_density_grid.png")
    return skip


def _write_report(all_A, out_dir: Path, overwrite, advance, instruments, observation, snapshots) -> Path:
    """Write figures/, summary.json and report.html, each through io.atomic_output (report.html last)."""
    A = all_A[0]
    with contextlib.ExitStack() as stack:
        # installed in the reverse order of entering: figures/, then summary.json, then report.html
        html_tmp = stack.enter_context(ctio.atomic_output(out_dir / "report.html", overwrite))
        json_tmp = stack.enter_context(ctio.atomic_output(out_dir / "summary.json", overwrite))
        fig_dir = stack.enter_context(ctio.atomic_output(out_dir / "figures", overwrite, folder=True))
        jobs = [
            ("fig7_4_incident_flux.png", lambda p: _fig_fluxes(A, p)),
            ("fig7_5_temperature.png", lambda p: _fig_temperature(A, p)),
            ("fig7_6_loose_minus_nominal.png", lambda p: _fig_dT_series(A, p)),
            ("fig7_7a_density_grid.png", lambda p: _fig_density_grid(A, p)),
            ("fig7_7b_regions.png", lambda p: _fig_regions(all_A, p)),
            ("fig7_8_night_map.png", lambda p: _fig_night_map(all_A, p)),
            ("fig7_9_quartiles.png", lambda p: _fig_quartiles(all_A, p)),
        ]
        if is_site(A):  # a DEM site: maps in the DEM's own coordinates replace the crater-centred plan view
            jobs = [(n, j) for n, j in jobs if n != "fig7_8_night_map.png"]
            jobs.append(("site_maps.png", lambda p: _fig_site_maps(A, p, instruments, observation)))
        jobs = [(n, j) for n, j in jobs if n not in _figures_without_data(A)]
        figures: List[str] = []
        note = None
        for name, job in jobs:
            job(fig_dir / name)
            figures.append(name)
            advance()
        summary = _summary(A, all_A[1:], instruments, observation, figures, None)
        if A.loose is not None:  # detection needs a loose profile
            _fig_detectability(summary, fig_dir / "detectability.png")
            figures.append("detectability.png")
        advance()
        if A.loose is not None:
            _fig_local_time(summary, fig_dir / "detection_local_time.png")
            figures.append("detection_local_time.png")
        advance()
        if summary["inversion_design"]:
            _fig_inversion_design(summary, fig_dir / "inversion_design.png")
            figures.append("inversion_design.png")
        if summary["detectability_vs_scatter"]:
            _fig_detectability_scatter(summary, fig_dir / "detectability_scatter.png")
            figures.append("detectability_scatter.png")
        advance()
        if snapshots:
            try:
                figures += _snapshots(A, fig_dir)
            except MissingExtraError as exc:
                note = f"3-D snapshots skipped: {exc}"
                print(f"note: {note}", file=sys.stderr)
            except CraterThermalError:
                raise
            except Exception as exc:  # rendering depends on OpenGL; the report must not
                note = f"3-D snapshots not rendered ({exc.__class__.__name__}: {' '.join(str(exc).split())[:200]})"
        else:
            note = "3-D snapshots not requested"
        advance()
        summary["figures"] = figures
        summary["snapshot_note"] = note
        json_tmp.write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
        html_tmp.write_text(
            _html(summary, fig_dir, {**FIGURES, **SNAPSHOTS, **SITE_FIGURES, **INVERSION_FIGURES}), encoding="utf-8"
        )
    return out_dir / "report.html"
