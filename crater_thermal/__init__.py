"""crater_thermal: thermal environment of lunar polar craters.

Data flow: case -> geometry -> fluxes -> temperatures -> analysis -> report.
SI units inside; named units (``lat_deg``, ``diameter_km``) only at the edges.

The Python API (:mod:`crater_thermal.api`) is re-exported here, imported on first use::

    import crater_thermal as ct
    run = ct.run(ct.load_case("cases/default.toml"))
"""

from crater_thermal._version import __version__ as __version__

#: The public API, from :mod:`crater_thermal.api` (no name equals a submodule's: ``import
#: crater_thermal.report`` would otherwise replace the function ``report`` with the module).
__all__ = [
    "load_case",
    "case_from_dict",
    "mesh_crater",
    "mesh_bowl",
    "mesh_dem",
    "load_mesh",
    "save_mesh",
    "run",
    "replay",
    "analyse",
    "steady_state",
    "make_report",
    "run_sweep",
    "export_map",
    "invert",
    "observation_design",
    "progress_callback",
    "Results",
]


def __getattr__(name):
    # lazily: `import crater_thermal` stays cheap (the CLI's --help, io's version stamp)
    if name in __all__:
        from crater_thermal import api

        return getattr(api, name)
    raise AttributeError(f"module 'crater_thermal' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
