"""The allowed names of crater_thermal.choices are exactly what the owning modules implement."""

from __future__ import annotations

from crater_thermal import (
    choices,
    config,
    ephemeris,
    illumination,
    io,
    materials,
    profiles,
    radiosity,
    thermal,
    vfoperator,
)

_MINIMAL = """
[crater]
diameter_km = 1.0
[location]
lat_deg = -85.0
[period]
start = "2019-01-01"
end = "2019-01-02"
"""


def test_owning_modules_implement_exactly_the_declared_names():
    assert set(illumination.LIMB_DARKENING_COEFFS) == set(choices.LIMB_DARKENING_LAWS)
    assert illumination.LIMB_DARKENING_LAWS is choices.LIMB_DARKENING_LAWS
    assert tuple(materials.PROPERTY_SETS) == choices.PROPERTY_SETS
    assert radiosity.SCATTERING_METHODS is choices.SCATTERING_METHODS
    assert vfoperator.METHODS is choices.VIEW_FACTOR_METHODS
    assert config.loads_case(_MINIMAL).radiation.tolerance == vfoperator.DEFAULT_TOLERANCE
    assert ephemeris.MOON_FRAMES is choices.MOON_FRAMES and ephemeris.SUN_CORRECTIONS is choices.SUN_CORRECTIONS
    assert ephemeris.ephemeris_range("de421") == choices.ephemeris_span("de421")
    assert tuple(io.SERIES_COMPRESSION) == choices.OUTPUT_COMPRESSIONS


def test_thermal_uses_the_base_profile_parser():
    """One parser: the case loader's (profiles) and the thermal model's give the same profile."""
    assert thermal.Profile is profiles.Profile
    assert materials.DENSITY_LIMITS is profiles.DENSITY_LIMITS
    for label in ("1300/1800", "rock", "hayne2017", "1500"):
        assert thermal.parse_profile(label, warn=False) == profiles.parse_profile(label)


def test_albedo_models_are_implemented():
    assert illumination.ALBEDO_MODELS is choices.ALBEDO_MODELS
    for model in choices.ALBEDO_MODELS:
        assert illumination.direct_albedo([[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0]], 0.12, model).shape == (1, 1)
