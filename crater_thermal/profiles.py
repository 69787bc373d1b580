"""Subsurface density profiles: what a profile label means and which profiles are allowed.

A profile is data (layers of density with depth), not physics, so it lives in the base layer:
:mod:`crater_thermal.config` validates the profile labels of a case file at load time with
:func:`parse_profile`, the same parser the thermal model uses (:mod:`crater_thermal.thermal`
re-exports :class:`Profile`, and its ``parse_profile`` adds the Table 7.2 extrapolation warning of
:mod:`crater_thermal.materials` on top of this one).

Labels
------
``"TOP/BOTTOM"``
    Two layers: ``TOP`` [kg m-3] over the top :data:`~crater_thermal.constants.TOP_LAYER_THICKNESS`
    (2 cm), ``BOTTOM`` down to the column depth (2 m) (thesis 7.1.2).
``"RHO"``
    Homogeneous regolith of density ``RHO`` [kg m-3].
``"rock"``
    Homogeneous rock, :data:`~crater_thermal.constants.ROCK_DENSITY` (3070 kg m-3).
``"hayne2017"``
    The exponential profile of Hayne et al. (2017): ``rho(z) = rho_d - (rho_d - rho_s) exp(-z/H)``,
    rho_s = 1100, rho_d = 1800 kg m-3, H = 6 cm.

Densities must lie in :data:`DENSITY_LIMITS` (500-3500 kg m-3: where the linear extrapolation of
thesis Table 7.2 still gives a positive, plausible conductivity) and must not decrease with depth
unless ``allow_inverted``; otherwise :class:`~crater_thermal.errors.ProfileError`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from crater_thermal.constants import COLUMN_DEPTH, LOOSE_PROFILE, NOMINAL_PROFILE, ROCK_DENSITY, TOP_LAYER_THICKNESS
from crater_thermal.errors import ProfileError

__all__ = [
    "Profile",
    "parse_profile",
    "check_profile",
    "check_density_limits",
    "density_grid_profiles",
    "grid_densities",
    "DENSITY_LIMITS",
    "HAYNE_LABEL",
    "HAYNE_RHO_S",
    "HAYNE_RHO_D",
    "HAYNE_H",
    "MAX_GRID_DENSITIES",
]

#: Densities [kg m-3] accepted at all (outside: ProfileError)
DENSITY_LIMITS = (500.0, 3500.0)
#: Label of the Hayne et al. 2017 exponential profile.
HAYNE_LABEL = "hayne2017"
#: Hayne et al. 2017 profile: surface and deep density [kg m-3], e-folding depth H [m]
HAYNE_RHO_S, HAYNE_RHO_D = 1100.0, 1800.0
HAYNE_H = 0.06
#: Most densities a density grid may have (91 profiles for the thesis's 13).
MAX_GRID_DENSITIES = 1000

_NUM = r"\s*([0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?)\s*"


@dataclass(frozen=True)
class Profile:
    """A subsurface density profile.

    Attributes
    ----------
    label : str
        e.g. ``"1300/1800"``, ``"rock"``, ``"hayne2017"``.
    layers : tuple of (bottom_depth_m, density_kg_m3)
        Layers from the top; the last one extends to the bottom of the column whatever its
        bottom depth. For the exponential ``hayne2017`` profile: ``((0.0, rho_s), (2.0, rho(2 m)))``
        (surface and bottom values, for labelling; the profile itself is ``exponential``).
    material : ``"regolith"`` or ``"rock"``
    exponential : (rho_s, rho_d, H_m) or None
        ``rho(z) = rho_d - (rho_d - rho_s) exp(-z / H)`` [kg m-3] (Hayne et al. 2017).
    """

    label: str
    layers: tuple
    material: str = "regolith"
    exponential: tuple | None = None

    @property
    def rho_top(self) -> float:
        """Density at the surface [kg m-3]."""
        return float(self.layers[0][1])

    @property
    def rho_bottom(self) -> float:
        """Density of the deepest layer (at 2 m for ``hayne2017``) [kg m-3]."""
        return float(self.layers[-1][1])

    @property
    def interfaces(self) -> tuple:
        """Depths [m] of the layer interfaces (where the grid puts a node)."""
        if self.exponential is not None:
            return ()
        return tuple(float(d) for d, _ in self.layers[:-1])

    def mean_density(self, za, zb):
        """Mean density [kg m-3] between depths ``za < zb`` [m] (arrays, exact integral)."""
        za = np.asarray(za, dtype=float)
        zb = np.asarray(zb, dtype=float)
        return (self._mass_to(zb) - self._mass_to(za)) / (zb - za)

    def mass_between(self, za, zb):
        """Areal mass [kg m-2] between depths ``za`` and ``zb`` [m]."""
        return self._mass_to(np.asarray(zb, float)) - self._mass_to(np.asarray(za, float))

    def _mass_to(self, z):
        z = np.asarray(z, dtype=float)
        if self.exponential is not None:
            rs, rd, H = self.exponential
            return rd * z - (rd - rs) * H * (1.0 - np.exp(-z / H))
        out = np.zeros_like(z)
        top = 0.0
        for i, (bottom, rho) in enumerate(self.layers):
            b = np.inf if i == len(self.layers) - 1 else float(bottom)
            out += rho * np.clip(np.minimum(z, b) - top, 0.0, None)
            top = b
        return out


def check_density_limits(rho, name: str = "density") -> None:
    """Raise :class:`ProfileError` if any density ``rho`` [kg m-3] lies outside :data:`DENSITY_LIMITS`."""
    r = np.atleast_1d(np.asarray(rho, dtype=float))
    bad = ~np.isfinite(r) | (r < DENSITY_LIMITS[0]) | (r > DENSITY_LIMITS[1])
    if np.any(bad):
        raise ProfileError(
            f"{name}={float(r[bad][0])!r} kg/m3 is outside the allowed range "
            f"{DENSITY_LIMITS[0]:.0f}-{DENSITY_LIMITS[1]:.0f} kg/m3"
        )


def check_profile(p: Profile, allow_inverted: bool = False) -> Profile:
    """Check a profile's material, layer depths and densities; return it unchanged.

    Raises
    ------
    ProfileError
        Unknown material, empty or non-increasing layers, an interface at or below the column
        bottom, a density outside :data:`DENSITY_LIMITS`, or (unless ``allow_inverted``) density
        decreasing with depth.
    """
    if p.material not in ("regolith", "rock"):
        raise ProfileError(f"profile {p.label!r}: material={p.material!r}; allowed 'regolith', 'rock'")
    if not p.layers:
        raise ProfileError(f"profile {p.label!r}: layers must not be empty")
    dens = np.array([float(r) for _, r in p.layers])
    depths = np.array([float(d) for d, _ in p.layers])
    check_density_limits(dens, name=f"profile {p.label!r} density")
    if p.exponential is None:
        if np.any(~np.isfinite(depths)) or np.any(depths <= 0) or np.any(np.diff(depths) <= 0):
            raise ProfileError(
                f"profile {p.label!r}: layer bottom depths {depths.tolist()} m must be positive and increasing"
            )
        if len(depths) > 1 and depths[-2] >= COLUMN_DEPTH:
            raise ProfileError(
                f"profile {p.label!r}: interface depth {depths[-2]} m must be < column depth {COLUMN_DEPTH} m"
            )
    if not allow_inverted and np.any(np.diff(dens) < 0):
        raise ProfileError(
            f"profile {p.label!r}: density decreases with depth ({dens.tolist()} kg/m3);"
            " allowed: top <= bottom (replay --allow-inverted, or allow_inverted=True in Python, accepts it)"
        )
    return p


def _hayne_profile() -> Profile:
    rs, rd, H = HAYNE_RHO_S, HAYNE_RHO_D, HAYNE_H
    rho2 = rd - (rd - rs) * math.exp(-COLUMN_DEPTH / H)
    return Profile(HAYNE_LABEL, ((0.0, rs), (COLUMN_DEPTH, rho2)), "regolith", (rs, rd, H))


def parse_profile(spec, allow_inverted: bool = False, label: str | None = None) -> Profile:
    """Build a checked :class:`Profile` from a label or a layer list.

    Parameters
    ----------
    spec : str, Profile or sequence of (bottom_depth_m, density_kg_m3)
        ``"1300/1800"``: top density over 2 cm, bottom density to 2 m; ``"1500"``: homogeneous;
        ``"rock"``: homogeneous rock, 3070 kg m-3; ``"hayne2017"``: exponential profile of
        Hayne et al. 2017 (1100 -> 1800 kg m-3, H = 6 cm); a layer list such as
        ``[(0.05, 1100), (2.0, 1700)]``.
    allow_inverted : bool
        Accept density decreasing with depth (otherwise ProfileError).
    label : str, optional
        Label for a layer list (default: ``"d1:rho1,d2:rho2,..."``).

    Raises
    ------
    ProfileError
        Not a label or layer list, or a profile :func:`check_profile` refuses.
    """
    if isinstance(spec, Profile):
        return check_profile(spec, allow_inverted)
    if isinstance(spec, str):
        s = spec.strip()
        if s.lower() == "rock":
            return Profile("rock", ((COLUMN_DEPTH, ROCK_DENSITY),), "rock")
        if s.lower() == HAYNE_LABEL:
            return check_profile(_hayne_profile(), allow_inverted)
        m2 = re.fullmatch(_NUM + "/" + _NUM, s)
        m1 = re.fullmatch(_NUM, s)
        if m2:
            top, bot = float(m2.group(1)), float(m2.group(2))
            p = Profile(label or f"{top:g}/{bot:g}", ((TOP_LAYER_THICKNESS, top), (COLUMN_DEPTH, bot)))
        elif m1:
            rho = float(m1.group(1))
            p = Profile(label or f"{rho:g}", ((COLUMN_DEPTH, rho),))
        else:
            raise ProfileError(
                f"profile={spec!r} is not understood; allowed: 'TOP/BOTTOM' densities in "
                "kg/m3 (e.g. '1300/1800'), a single density, 'rock', 'hayne2017'"
            )
        return check_profile(p, allow_inverted)
    try:
        layers = tuple((float(d), float(r)) for d, r in spec)
    except (TypeError, ValueError):
        raise ProfileError(f"profile={spec!r} is not a label or a list of (bottom_depth_m, density) pairs") from None
    lab = label or ",".join(f"{d:g}:{r:g}" for d, r in layers)
    return check_profile(Profile(lab, layers), allow_inverted)


def grid_densities(spec: str) -> np.ndarray:
    """The densities [kg m-3] of a density grid ``"start:stop:step"`` (stop inclusive), checked.

    Raises
    ------
    ProfileError
        Not ``start:stop:step``, step <= 0, start > stop, more than :data:`MAX_GRID_DENSITIES`
        densities, or a density outside :data:`DENSITY_LIMITS`.
    """
    m = re.fullmatch(_NUM + ":" + _NUM + ":" + _NUM, str(spec))
    if not m:
        raise ProfileError(f"density_grid={spec!r} is not 'start:stop:step' in kg/m3 (e.g. '800:2000:100')")
    a, b, step = (float(g) for g in m.groups())
    if not (step > 0) or b < a:
        raise ProfileError(f"density_grid={spec!r}: need step > 0 and start <= stop")
    n = int(math.floor((b - a) / step + 1e-9)) + 1
    if n > MAX_GRID_DENSITIES:
        raise ProfileError(f"density_grid={spec!r} gives {n} densities; allowed at most {MAX_GRID_DENSITIES}")
    dens = a + step * np.arange(n)
    check_density_limits(dens, name=f"density_grid {spec!r} density")
    return dens


def density_grid_profiles(spec: str) -> tuple:
    """All two-layer profiles ``top/bottom`` with top <= bottom on a density grid.

    Parameters
    ----------
    spec : ``"start:stop:step"`` [kg m-3], stop inclusive (``"800:2000:100"`` gives 13 densities
        and 91 profiles).

    Returns
    -------
    tuple of Profile, ordered by top density then bottom density.
    """
    dens = grid_densities(spec)
    out = []
    for i, top in enumerate(dens):
        for bot in dens[i:]:
            out.append(parse_profile(f"{top:g}/{bot:g}"))
    return tuple(out)


# ----------------------------------------------------------------------------- labels


def profile_label(top_bottom) -> str:
    """Label of a two-layer profile, e.g. ``(1300.0, 1800.0) -> "1300/1800"``."""
    return f"{top_bottom[0]:g}/{top_bottom[1]:g}"


def parse_two_layer(label: str) -> tuple[float, float] | None:
    """``(top, bottom)`` densities [kg m-3] of a two-layer label such as ``"1300/1800"``; None otherwise."""
    try:
        a, b = str(label).split("/")
        return float(a), float(b)
    except ValueError:
        return None


def is_rock(label: str) -> bool:
    """Whether a profile label names solid rock (``"rock"``, any case): the label parsed, not searched."""
    try:
        return parse_profile(str(label)).material == "rock"
    except ProfileError:
        return False


#: Label of the nominal (compact) profile of the thesis, top/bottom [kg m-3]: the default of a run.
NOMINAL_LABEL = profile_label(NOMINAL_PROFILE)
#: Label of the thesis's loose profile [kg m-3].
LOOSE_LABEL = profile_label(LOOSE_PROFILE)
#: Profiles a replay uses when none are given: nominal, loose and rock.
DEFAULT_REPLAY_PROFILES = (NOMINAL_LABEL, LOOSE_LABEL, "rock")


def unique_profiles(profiles) -> list:
    """``profiles`` without repeated labels (the first kept, order kept)."""
    seen, unique = set(), []
    for p in profiles:
        if p.label not in seen:
            seen.add(p.label)
            unique.append(p)
    return unique
