"""The answer in plain words: the headline of a report, written from its numbers (``summary.json``).

:func:`headline` turns a report's summary into a short paragraph: how much colder the loose profile is
than the nominal one at night (typical and largest, and where), when to look, which instrument sees it
with how long an exposure or what stops it, and how that answer moves with the footprint-to-footprint
natural scatter over its plausible range. The report opens on it, ``crater-thermal report`` and
``crater-thermal summary`` print it. :func:`region_words` names the report's regions for a reader;
:data:`GLOSSARY` explains the terms the report uses. Nothing here computes physics: every number comes
from the summary, so the headline and ``summary.json`` always agree.
"""

from __future__ import annotations

import math
from typing import Optional

#: Words for the crater parts and classes of :mod:`crater_thermal.regions`.
_PARTS = {
    "floor": "crater floor",
    "lower_wall": "lower crater wall",
    "upper_wall": "upper crater wall",
    "top_wall_ring": "top of the wall (the ring at the crest)",
    "rim": "outer flank of the rim",
    "surround": "plain around the crater",
    "never_lit": "facets never in direct sunlight",
    "rarely_lit": "facets rarely in direct sunlight (< 10 % of the time)",
    "often_lit": "facets often in direct sunlight",
}
_SIDES = {
    "pole_facing": "pole-facing side",
    "equator_facing": "equator-facing side (on the pole side of the crater, facing the Sun)",
    "east_facing": "east-facing side",
    "west_facing": "west-facing side",
    "sun_facing": "Sun-facing side",
    "antisun_facing": "side facing away from the Sun",
    "sun_left_facing": "side left of the Sun",
    "sun_right_facing": "side right of the Sun",
}

#: The terms of the report, explained (shown as the report's glossary).
GLOSSARY = {
    "nominal, loose": "the compact density profile of the run (thesis: 1300 kg m-3 in the top 2 cm over 1800 kg m-3 "
    "below) and the loose one it is compared with (thesis: 800/1100); loose regolith conducts heat worse, so it "
    "cools faster and further at night",
    "dT": "loose minus nominal surface temperature of the same facet at the same time [K]; negative: loose is colder",
    "night": "the samples counted as night for a facet (the definition is stated in the report: by default the "
    "facet has had no sunlight for a stated time)",
    "night median": "the median over a region's facets and night samples",
    "natural scatter": "how much the true temperatures of otherwise alike footprints differ [K] (rocks, slopes, "
    "local density); it does not average down with longer looks, so it can cap the detection probability",
    "NETD": "noise-equivalent temperature difference of one integration of the instrument [K], at the scene "
    "temperature",
    "1/f floor (allan floor)": "the noise level below which averaging stops helping (the instrument's 1/f knee)",
    "P_D": "detection probability: the chance that a loose patch is flagged, with the false-alarm rate fixed",
    "false alarm": "the chance that compact regolith is flagged as loose (1 % by default)",
    "exposure": "a stare of so many seconds on each footprint, or a number of orbital passes (Diviner: 0.128 s "
    "on a footprint per pass)",
    "footprints": "the candidate patch spans k instrument footprints and is compared with m reference footprints",
}


def region_words(name: str) -> str:
    """A reader's name for a region of :mod:`crater_thermal.regions` (``upper_wall_equator_facing`` ->
    "upper crater wall, equator-facing side (...)"; slope classes ``slope_5_15_deg`` -> "slopes 5-15 deg")."""
    if name in _PARTS:
        return _PARTS[name]
    for side, words in _SIDES.items():
        if name.endswith("_" + side):
            part = name[: -len(side) - 1]
            return f"{_PARTS.get(part, part.replace('_', ' '))}, {words}"
    if name in _SIDES:  # a DEM site's facing classes
        words = _SIDES[name].split(" (")[0]
        return words[: -len(" side")] + " slopes" if words.endswith(" side") else "slopes on the " + words
    if name == "level":
        return "level ground (slopes below 5 deg)"
    if name.startswith("slope_") and name.endswith("_deg"):
        lo, _, hi = name[len("slope_") : -len("_deg")].partition("_")
        return f"slopes {lo}-{hi} deg" if hi else f"slopes above {lo} deg"
    if name.startswith("facing_"):
        return f"slopes facing {name[len('facing_') :].replace('_', ' ')}"
    return name.replace("_", " ")


def _fmt_K(v: float) -> str:
    return f"{abs(v):.1f} K"


def _exposure(row: dict) -> str:
    """``"52 passes (6.7 s on each footprint)"`` or ``"6.7 s"`` from a detection row."""
    if row.get("exposure_unit") == "passes" and row.get("passes"):
        n = int(row["passes"])
        return f"{n} pass{'es' if n != 1 else ''} ({row['dwell_s']:.2g} s on each footprint)"
    return f"a {row['dwell_s']:.2g} s stare"


def _scatter_exposure(seconds: Optional[float], row: dict) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "not at all"
    per_pass = row.get("pass_integration_s")
    if row.get("exposure_unit") == "passes" and per_pass:
        n = max(1, math.ceil(seconds / per_pass - 1e-9))
        return f"after {n} pass{'es' if n != 1 else ''}"
    return f"after a {seconds:.2g} s stare"


def focus_region(summary: dict) -> Optional[str]:
    """The region the headline's detection sentence is about: the crater floor when there is one, else the
    region with the largest night-time contrast (a DEM site)."""
    loose = summary.get("loose_profile")
    med = (summary.get("night_median_dT_K") or {}).get(loose) or {}
    valid = {r: v for r, v in med.items() if v is not None}
    if not valid:
        return None
    if "floor" in valid:
        return "floor"
    return max(valid, key=lambda r: abs(valid[r]))


def headline(summary: dict) -> str:
    """The report's answer as a plain-text paragraph (units in the text), computed from ``summary``."""
    loose, nominal = summary.get("loose_profile"), summary.get("nominal_profile")
    where = "this site" if summary.get("site") else "this crater"
    lat = summary.get("lat_deg")
    if not loose:
        profiles = ", ".join(p for p in summary.get("profiles", []) if p != nominal) or "none"
        return (
            f"This replay has no loose profile to compare with the nominal {nominal} (replayed: {profiles}), so "
            "there is no loose - nominal night-time contrast to report; replay with --profile 800/1100 (or a "
            "--density-grid) to answer the question."
        )
    med = {r: v for r, v in summary["night_median_dT_K"][loose].items() if v is not None}
    if not med:
        return f"No facet of {where} has night-time samples in this run, so no night-time contrast can be given."
    values = sorted(med.values())
    typical = (
        values[len(values) // 2] if len(values) % 2 else 0.5 * (values[len(values) // 2 - 1] + values[len(values) // 2])
    )
    largest = max(med, key=lambda r: abs(med[r]))
    colder = "colder" if typical < 0 else "warmer"
    sentences = [
        f"At night, loose regolith ({loose} kg m-3) is typically {_fmt_K(typical)} {colder} than the nominal "
        f"{nominal} kg m-3 at {where} (lat {lat:g} deg; night median over its regions), and up to "
        f"{_fmt_K(med[largest])} on the {region_words(largest)}."
    ]
    focus = focus_region(summary)
    det = summary.get("detection") or {}
    rows = {name: per[focus] for name, per in det.items() if focus in per and per[focus].get("T_nominal_K")}
    if focus is not None and focus != largest:
        T = (summary.get("night_median_T_nominal_K") or {}).get(focus)
        on = f" (nominal night temperature {T:.1f} K)" if T else ""
        sentences.append(f"On the {region_words(focus)}{on} the contrast is {_fmt_K(med[focus])}.")
    times = [r.get("best_local_time_h") for r in rows.values() if r.get("best_local_time_h") is not None]
    if times:
        sentences.append(
            f"It stands out most against the noise at about {sorted(times)[len(times) // 2]:.0f} h local solar time "
            "(0 h: midnight)."
        )
    obs = summary.get("observation") or {}
    s = obs.get("natural_scatter_K")
    k, m = obs.get("candidate_footprints", 1), obs.get("reference_footprints", 1)
    patch = f"a loose patch of {k} footprint{'s' if k != 1 else ''} against {m} reference{'s' if m != 1 else ''}"
    seen = {n: r for n, r in rows.items() if r.get("detectable")}
    far = f"P_D >= {obs.get('target_pd', 0.9):g} at {100 * obs.get('false_alarm', 0.01):g} % false alarms"
    if seen:
        best = min(seen, key=lambda n: seen[n]["dwell_s"])
        others = [f"{n} {_exposure(r)}" for n, r in seen.items() if n != best]
        sentences.append(
            f"With {patch} and {s:g} K natural scatter, {best} reaches {far} with {_exposure(seen[best])}"
            + (f" (also: {'; '.join(others)})" if others else "")
            + (f"; {', '.join(n for n in rows if n not in seen)} cannot." if len(seen) < len(rows) else ".")
        )
    elif rows:
        limits = sorted({(r.get("limiting_term") or "?").replace("_", " ") for r in rows.values()})
        caps = max(r.get("pd_limit") or 0.0 for r in rows.values())
        sentences.append(
            f"With {patch} and {s:g} K natural scatter, no instrument reaches {far} at any exposure (the best "
            f"reaches P_D {caps:.2f}); what stops it: {', '.join(limits)}."
        )
    larger = summary.get("detection_larger_patch")
    if rows and not seen and larger:
        by = {n: r for n, r in larger["by_instrument"].items() if r.get("detectable")}
        kk, mm = larger["candidate_footprints"], larger["reference_footprints"]
        if by:
            n1 = min(by, key=lambda n: by[n]["dwell_s"])
            sentences.append(
                f"A loose patch of {kk} footprints against {mm} references would be seen by {n1} with "
                f"{_exposure(by[n1])}."
            )
        else:
            cap = max(r.get("pd_limit") or 0.0 for r in larger["by_instrument"].values())
            sentences.append(
                f"Even a loose patch of {kk} footprints against {mm} references would not be seen (P_D at most "
                f"{cap:.2f})."
            )
    if rows and s:
        n0 = min(rows, key=lambda n: rows[n].get("dwell_s_scatter_half") or math.inf)
        half, double = rows[n0].get("dwell_s_scatter_half"), rows[n0].get("dwell_s_scatter_double")
        sentences.append(
            f"The answer hangs on the natural scatter, measured by Diviner only at warmer, non-polar regolith: "
            f"at {s / 2:g} K {n0} would see it {_scatter_exposure(half, rows[n0])}, at {2 * s:g} K "
            f"{_scatter_exposure(double, rows[n0])}."
        )
    return " ".join(sentences)
