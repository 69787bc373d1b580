"""The Python API: build a case, run it, replay it, analyse it and report it, from a script or a notebook.

Everything the command line does goes through these functions (``crater_thermal.cli`` only parses
arguments and prints). They are re-exported by the package::

    import crater_thermal as ct

    case = ct.load_case("cases/default.toml", {"period.end": "2019-02-01"})
    run = ct.run(case)                                  # xarray.Dataset, fluxes and temperatures
    rep = ct.replay(run, profiles=["800/1100", "rock"])  # the saved fluxes against other densities
    res = ct.analyse(run, rep)                           # the report's numbers, without files
    res.night_median_dT_K["floor"]                       # loose - nominal, night median [K]

Units: SI inside (K, W m-2, m, s); named units in argument names (``lat_deg``, ``diameter_km``).
Errors: invalid input raises a :class:`crater_thermal.errors.CraterThermalError` (the command line's
exit code 2) before any work; a failure inside raises :class:`crater_thermal.errors.InternalError`
(exit code 3). Progress: ``progress=True`` draws a bar on a terminal or in a notebook (plain lines in
a log), ``None``/``False`` nothing, or pass your own reporter (see :func:`progress_callback`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Optional, Sequence, Union

from crater_thermal import config, geometry, gis, io, progress, runner
from crater_thermal.errors import ConfigError

if TYPE_CHECKING:
    from crater_thermal.config import Case
    from crater_thermal.geometry import Mesh

PathLike = Union[str, os.PathLike]
#: An ``xarray.Dataset`` (only :mod:`crater_thermal.io` imports xarray).
Dataset = Any


# ----------------------------------------------------------------------------- cases


def load_case(path: PathLike, overrides: Optional[Mapping[str, Any]] = None, name: Optional[str] = None) -> "Case":
    """Read and validate a case file (TOML; keys in ``cases/README.md``), optionally with overrides.

    Parameters
    ----------
    path : path-like
        The case file.
    overrides : mapping, optional
        Dotted keys to change, e.g. ``{"location.lat_deg": -80.0, "period.end": "2019-03-01"}``;
        a value of None restores a key's default. The result is validated again.
    name : str, optional
        A new case name (default: the file's).

    Returns
    -------
    Case
    """
    case = config.load_case(path)
    if overrides or name:
        case = case.with_overrides(dict(overrides or {}), name=name)
    return case


def case_from_dict(sections: Mapping[str, Any], name: str = "case", base_dir: Optional[PathLike] = None) -> "Case":
    """A validated case from a dictionary shaped like a case file.

    ``{"crater": {"kind": "crater", "diameter_km": 2.0, "facets": 150}, "location": {"lat_deg": -85.0},
    "period": {"start": "2019-01-01", "end": "2019-02-01"}}``. Relative paths (a mesh, a DEM) are
    read from ``base_dir`` (default: the current folder).
    """
    raw = dict(sections)
    raw.setdefault("name", name)
    text = config.dump_toml(raw)
    return config.loads_case(text, base_dir=Path(base_dir or os.getcwd()), name=raw["name"])


# ----------------------------------------------------------------------------- meshes


def mesh_crater(diameter_km: float = 10.0, facets: int = 502, surround_km: float = 0.0, wall: str = "thesis") -> "Mesh":
    """The idealized simple crater of thesis Table 7.1 (rim diameter [km], exact facet count, optional flat
    surround [km]); vertices in metres, x east, y north, z up, the rim plane at z = 0."""
    return geometry.crater_mesh(diameter_km=diameter_km, n_facets=facets, surround_km=surround_km, wall=wall)


def mesh_bowl(depth_to_diameter: float = 0.2, facets: int = 3000, diameter_m: float = 1000.0) -> "Mesh":
    """Ingersoll et al. (1992)'s spherical-cap bowl: depth / diameter, exact facet count, rim diameter [m]."""
    return geometry.bowl_mesh(depth_to_diameter=depth_to_diameter, n_facets=facets, diameter_m=diameter_m)


def mesh_dem(dem: PathLike, center_lat_deg: float, center_lon_deg: float, radius_km: float, **options) -> "Mesh":
    """A site of a polar DEM as a mesh in the centre's east/north/up frame [m].

    ``options`` are those of ``crater-thermal mesh dem`` (see :func:`crater_thermal.terrain.site_mesh`):
    ``resolution_m``, ``outer_radius_km``, ``outer_resolution_m``, ``height_kind``, ``max_facets`` and
    the metadata overrides for files that lack or misstate it.
    """
    from crater_thermal import terrain

    return terrain.site_mesh(dem, center_lat_deg, center_lon_deg, radius_km, **options)


def load_mesh(path: PathLike, flip: bool = False) -> "Mesh":
    """Read a mesh (.ply, .obj, .stl) [m]; ``flip`` reverses every facet's winding."""
    return geometry.load_mesh(path, flip=flip)


def save_mesh(mesh: "Mesh", path: PathLike, overwrite: bool = False) -> Path:
    """Write a mesh (.ply keeps the site metadata, .obj, .stl) atomically; returns the path."""
    return geometry.save_mesh(mesh, path, overwrite=overwrite)


# ----------------------------------------------------------------------------- progress


def progress_callback(fn: Callable[[str, int, int], None]) -> progress.Reporter:
    """A progress reporter calling ``fn(stage, done, total)``: hook any display (a notebook widget, a log).

    >>> rep = progress_callback(lambda stage, done, total: print(stage, done, total))  # doctest: +SKIP
    >>> ct.run(case, progress=rep)                                                     # doctest: +SKIP
    """

    @contextlib.contextmanager
    def stage(description: str):
        yield lambda done, total: fn(description, done, total)

    return stage


def _reporter(p):
    if p is None or p is False:
        return None
    if p is True:
        return progress.reporter(True)
    if callable(p):
        return p
    raise ConfigError(f"progress={p!r}: use True, False/None, or a reporter (see progress_callback)")


# ----------------------------------------------------------------------------- running


@contextlib.contextmanager
def _scratch_folder():
    folder = tempfile.mkdtemp(prefix="crater_thermal_")
    try:
        yield Path(folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _in_memory(path: Path, opener) -> Dataset:
    ds = opener(path)
    ds.load()  # in memory: the file can go
    ds.close()
    return ds


def run(
    case: Union["Case", PathLike],
    out: Optional[PathLike] = None,
    *,
    resume: bool = False,
    overwrite: bool = False,
    progress: Any = None,
    scheduler: Optional[str] = None,
    workers: Optional[int] = None,
    chunk_facets: Optional[int] = None,
) -> Dataset:
    """Run a case: sunlight, scattering, infrared exchange and conduction over the case's period.

    Parameters
    ----------
    case : Case or path-like
        A case (:func:`load_case`, :func:`case_from_dict`) or a case file.
    out : path-like, optional
        Write the run dataset there (netCDF, streamed block by block: memory stays bounded for any
        run length), checkpointed for ``resume``. Without it the run goes to a temporary file and
        comes back in memory (for runs that fit: time x facets x 4 series x 4 bytes).
    resume : bool
        Continue from the checkpoint beside ``out``.
    overwrite : bool
        Replace an existing ``out``.
    progress : bool or reporter, optional
    scheduler : str, optional
        Address of a dask.distributed scheduler (``tcp://host:8786``): the columns are conducted in
        chunks by its workers, coupled by waveform relaxation (``[steps] ir_coupling = "relaxed"``
        whatever the case says; :mod:`crater_thermal.cluster_run`). The scratch store beside ``out``
        (``OUT.partial/``) must be readable by every worker at the same path.
    workers : int, optional
        Instead of ``scheduler``: a local dask cluster of this many one-thread processes.
    chunk_facets : int, optional
        With ``scheduler`` or ``workers``: at most this many facets per chunk (one task per chunk and
        relaxation iteration). Default: one chunk per worker present at the start (the fastest measured:
        docs/cluster.md); smaller chunks let workers that join later take some.

    Returns
    -------
    xarray.Dataset
        The run (schema in :mod:`crater_thermal.io`): opened lazily from ``out`` when given (close it,
        or use it in a ``with`` block), in memory otherwise.
    """
    case = case if isinstance(case, config.Case) else config.load_case(case)
    rep = _reporter(progress)
    columns = None
    if scheduler is not None or workers is not None:
        if scheduler is not None and workers is not None:
            raise ConfigError("--scheduler and --workers: give one (a remote scheduler, or a local cluster)")
        if scheduler is None and int(workers) < 1:
            raise ConfigError(f"--workers {workers}: need at least 1 worker process")
        if out is None:
            raise ConfigError("a run on a dask cluster needs out: its scratch store beside it is what workers read")
        from crater_thermal import cluster_run

        columns = cluster_run.distributed_columns(scheduler, workers, chunk_facets)
    if out is None:
        if resume:
            raise ConfigError("resume needs out: the run's file and its checkpoint")
        with _scratch_folder() as d:
            path = runner.run_case(case, d / "run.nc", progress=rep)
            return _in_memory(path, io.open_run)
    path = runner.run_case(case, out, resume=resume, overwrite=overwrite, progress=rep, columns=columns)
    return io.open_written(path)


def replay(
    run: Union[Dataset, PathLike],
    profiles: Sequence[str] = (),
    *,
    density_grid: Optional[str] = None,
    out: Optional[PathLike] = None,
    overwrite: bool = False,
    initial_temperature_K: Optional[float] = None,
    fixed_spinup: bool = False,
    property_set: Optional[str] = None,
    allow_inverted: bool = False,
    progress: Any = None,
    scheduler: Optional[str] = None,
    workers: Optional[int] = None,
    chunk_facets: int = 2000,
    chunk_profiles: int = 8,
    resume: bool = False,
) -> Dataset:
    """Replay a run's saved fluxes against other density profiles (the IR stays the run's, thesis 7.2).

    Parameters
    ----------
    run : Dataset or path-like
        A run (or any flux dataset with ``solar_incident`` and ``ir_incident`` [W m-2]).
    profiles : sequence of str
        ``"TOP/BOTTOM"`` densities [kg m-3] of the top 2 cm and below, ``"rock"``, ``"hayne2017"``.
        Default (with no ``density_grid``): nominal, loose (800/1100) and rock.
    density_grid : str, optional
        ``"START:STOP:STEP"`` [kg m-3]: every top <= bottom pair of the grid.
    out : path-like, optional
        Write the replay there (netCDF); default: in memory.
    initial_temperature_K, fixed_spinup :
        The thesis's procedure instead of the periodic steady state (see ``crater-thermal replay``).
    property_set : "apollo" | "hayne2017", optional
        Default: the run's.
    scheduler : str, optional
        Address of a dask.distributed scheduler (``tcp://host:8786``): the columns are solved in
        chunks by its workers, which read ``run``'s file at the same path (a shared filesystem);
        the results come back to this process, which writes ``out``. The temperatures equal a
        local replay's. Needs the ``distributed`` extra (see :doc:`/cluster`).
    workers : int, optional
        Instead of ``scheduler``: a local dask cluster of this many one-thread processes.
    chunk_facets, chunk_profiles : int
        With ``scheduler`` or ``workers``: facets and profiles of one task (chunk).
    resume : bool
        With ``scheduler`` or ``workers``: keep the finished chunks of an interrupted replay with the
        same ``out``, inputs, profiles, options and chunking (saved in ``OUT.chunks/``).

    Returns
    -------
    xarray.Dataset
        ``surface_temperature(profile, time, facet)`` [K], lazily from ``out`` or in memory.
    """
    rep = _reporter(progress)
    kw = dict(
        density_grid=density_grid,
        initial_temperature=initial_temperature_K,
        fixed_spinup=fixed_spinup,
        property_set=property_set,
        allow_inverted=allow_inverted,
        progress=rep,
    )
    if scheduler is not None or workers is not None:
        from crater_thermal import cluster

        if scheduler is not None and workers is not None:
            raise ConfigError("--scheduler and --workers: give one (a remote scheduler, or a local cluster)")
        flux = _file_of(run)
        if flux is None:
            raise ConfigError(
                "a replay on a dask cluster reads the run from a file every worker can open: save the dataset "
                "(ds.to_netcdf(path)) and pass the path"
            )
        kw.update(
            scheduler=scheduler,
            workers=workers,
            chunk_facets=chunk_facets,
            chunk_profiles=chunk_profiles,
            resume=resume,
        )
        replay_file = cluster.replay_file
    elif resume:
        raise ConfigError("--resume continues a replay on a dask cluster; give --scheduler or --workers")
    else:
        replay_file = runner.replay_file
    with _scratch_folder() as d:
        flux = _as_file(run, d / "flux.nc")
        if out is None:
            path = replay_file(flux, list(profiles), output=d / "replay.nc", **kw)
            return _in_memory(path, io.open_replay)
        path = replay_file(flux, list(profiles), output=out, overwrite=overwrite, **kw)
    return io.open_written(path)


def _file_of(ds_or_path) -> Optional[Path]:
    """The file a dataset was opened from (or the path itself); None for a dataset only in memory."""
    if isinstance(ds_or_path, (str, os.PathLike)):
        return Path(ds_or_path)
    source = ds_or_path.encoding.get("source")
    return Path(source) if source and os.path.isfile(source) else None


def _as_file(ds_or_path, scratch: Path) -> Path:
    """The file of a dataset: its own path, the file it was opened from, or a scratch copy."""
    path = _file_of(ds_or_path)
    if path is not None:
        return path
    io.write_dataset_atomic(ds_or_path, scratch)
    return scratch


# ----------------------------------------------------------------------------- analysis and report


@dataclass(frozen=True)
class Results:
    """The numbers of a report (:func:`analyse`): what the report and ``summary.json`` say.

    Attributes
    ----------
    summary : dict
        The whole ``summary.json`` content (keys documented in the report's docs).
    nominal, loose : str
        The nominal and loose profile labels (``loose`` None without a loose profile).
    night_median_dT_K : dict
        Region -> night median of loose - nominal surface temperature [K] (negative: loose is colder).
    night_median_T_nominal_K : dict
        Region -> night median of the nominal surface temperature [K].
    """

    summary: dict = field(repr=False)
    nominal: str
    loose: Optional[str]
    night_median_dT_K: dict
    night_median_T_nominal_K: dict

    @property
    def headline(self) -> str:
        """The answer in plain words, as the report opens on it (:func:`crater_thermal.answer.headline`)."""
        return self.summary["headline"]

    def __repr__(self) -> str:
        lines = [f"Results(nominal={self.nominal!r}, loose={self.loose!r}; night median loose - nominal [K]:"]
        for region, dT in self.night_median_dT_K.items():
            lines.append(f"  {region}: {'n/a' if dT is None else format(dT, '+.2f')}")
        return "\n".join(lines) + ")"


def analyse(
    run: Union[Dataset, PathLike],
    replay: Union[Dataset, PathLike],
    *,
    instruments: Optional[Sequence[str]] = None,
    natural_scatter_K: Optional[float] = None,
    night: str = "dark",
    min_dark_hours: Optional[float] = None,
) -> Results:
    """The report's numbers for a run and its replay, without writing anything.

    ``instruments``: preset channel names (default: all presets); ``natural_scatter_K``: footprint-to-
    footprint scatter of true temperatures [K] (default the report's); ``night``: the night definition
    (``dark``, the default, ``facet``, ``centre``, ``facet_and_centre``:
    :func:`crater_thermal.regions.night_selection`); ``min_dark_hours`` [h].
    """
    from crater_thermal import instrument as ins
    from crater_thermal import regions
    from crater_thermal import report as rp

    insts = None if instruments is None else [ins.get_instrument(n) for n in instruments]
    obs = ins.Observation() if natural_scatter_K is None else ins.Observation(natural_scatter_K=natural_scatter_K)
    s = rp.summarize(
        run,
        replay,
        instruments=insts,
        observation=obs,
        night_definition=night,
        min_dark_hours=regions.MIN_DARK_HOURS if min_dark_hours is None else min_dark_hours,
    )
    loose = s.get("loose_profile")
    return Results(
        summary=s,
        nominal=s.get("nominal_profile"),
        loose=loose,
        night_median_dT_K=dict(s.get("night_median_dT_K", {}).get(loose, {})) if loose else {},
        night_median_T_nominal_K=dict(s.get("night_median_T_nominal_K", {})),
    )


def make_report(
    run: Union[Dataset, PathLike, Sequence],
    replay: Union[Dataset, PathLike, Sequence, None],
    out_dir: PathLike,
    *,
    overwrite: bool = False,
    progress: Any = None,
    **options,
) -> Path:
    """Write ``report.html``, ``summary.json`` and ``figures/`` into ``out_dir``; returns report.html's path.

    ``run``/``replay``: datasets or paths (lists for several latitudes; a sweep's output folder as
    ``run`` with ``replay=None``). ``options``: those of :func:`crater_thermal.report.make_report`
    (``instruments``, ``observation``, ``snapshots``, ``night_definition``, ``min_dark_hours``).
    """
    from crater_thermal import report as rp

    flag = None if progress is None else bool(progress)
    return rp.make_report(run, replay, out_dir, overwrite=overwrite, progress=flag, **options)


def steady_state(
    mesh: Union["Mesh", PathLike],
    sun_elevation_deg: float,
    sun_azimuth_deg: float = 180.0,
    *,
    out: Optional[PathLike] = None,
    overwrite: bool = False,
    progress: Any = None,
    **options,
) -> Dataset:
    """Radiative equilibrium of a mesh under a fixed Sun at 1 au (no conduction; ``crater-thermal steady``).

    Parameters
    ----------
    mesh : Mesh or path-like
        A mesh (:func:`mesh_crater`, :func:`mesh_dem`, ...) or a mesh file (.ply, .obj, .stl) [m].
    sun_elevation_deg, sun_azimuth_deg : float [deg]
        The Sun's elevation and its azimuth from north, clockwise.
    out : path-like, optional
        Write the result there (netCDF); default: in memory.
    options :
        Those of :func:`crater_thermal.steady.steady_file`: ``albedo``, ``emissivity`` [-],
        ``solar_constant`` [W m-2], ``point_sun``, ``limb_darkening``, ``n_rings``, ``method`` and
        ``n_bounces`` (scattering), ``view_factors`` and ``tolerance`` (the operator, chosen by size as a
        run does), ``solver``, ``flip``.

    Returns
    -------
    xarray.Dataset
        ``surface_temperature(facet)`` [K], ``solar_direct``, ``solar_incident``, ``ir_incident`` [W m-2],
        the mesh, and attributes naming the methods used.
    """
    from crater_thermal import steady as st

    flag = None if progress is None else bool(progress)
    with _scratch_folder() as d:
        path = mesh
        if isinstance(mesh, geometry.Mesh):
            path = geometry.save_mesh(mesh, d / "mesh.ply")
        target = d / "steady.nc" if out is None else out
        written, _ = st.steady_file(
            path, target, sun_elevation_deg, sun_azimuth_deg, overwrite=overwrite, progress=flag, **options
        )
        if out is None:
            return _in_memory(written, io.open_written)
    return io.open_written(written)


def run_sweep(
    cases: Sequence[PathLike], out_dir: PathLike, *, scheduler: Optional[str] = None, workers=None, progress=None
):
    """Run many case files and their replays into ``out_dir/CASE/`` (local processes or a dask scheduler);
    returns one summary dict per case. A restarted sweep skips what is finished."""
    from crater_thermal import sweep as sw

    return sw.sweep(cases, out_dir, scheduler=scheduler, workers=workers, progress=progress)


def export_map(
    source: PathLike,
    output: PathLike,
    variable: str = "surface_temperature",
    statistic: str = "night_median",
    *,
    time: Optional[str] = None,
    profile: Optional[str] = None,
    run: Optional[PathLike] = None,
    pixel_m: Optional[float] = None,
    night: Optional[str] = None,
    overwrite: bool = False,
) -> Path:
    """Rasterize a per-facet statistic of a run or replay file to a GeoTIFF (``crater-thermal export``).

    ``variable``: a run's ``surface_temperature`` [K] or a flux (``solar_incident``, ``solar_direct``,
    ``ir_incident``, ``solar_absorbed`` [W m-2]); a replay's ``surface_temperature`` of ``profile`` [K] or
    ``profile_minus_nominal`` [K] (``profile="800/1100"``: loose - nominal). ``statistic``:
    ``night_median`` (per-facet night, :func:`crater_thermal.regions.night_day_masks`; a replay needs its
    ``run``), ``mean``, ``min``, ``max`` or ``at`` with ``time`` (ISO UTC, nearest sample). The map is in
    the DEM's CRS for a DEM site (its analysed facets only), else in a crater-centred lunar azimuthal
    equidistant CRS [m]; ``pixel_m`` [m] defaults to the mean facet edge; NaN outside the mesh. See
    :mod:`crater_thermal.gis`. A posterior of :func:`invert` (with its ``run``) maps ``p_loose`` (a site's
    P(loose) map) or the MAP/mean/sd densities per footprint. Returns the GeoTIFF's path.
    """
    return gis.export_map(
        source,
        output,
        variable,
        statistic,
        time=time,
        profile=profile,
        run=run,
        pixel_m=pixel_m,
        night=night,
        overwrite=overwrite,
    )


def _forward_model(run, grid_replay):
    """(run dataset, inversion.ForwardModel) of a run and its density-grid replay (paths or Datasets)."""
    import numpy as np

    from crater_thermal import inversion

    run_ds = io.open_run(run, load=False) if isinstance(run, (str, os.PathLike)) else run
    rep = io.open_replay(grid_replay) if isinstance(grid_replay, (str, os.PathLike)) else grid_replay
    io.check_pair(run_ds, rep)
    tops = np.asarray(rep["rho_top"].values, float)
    bots = np.asarray(rep["rho_bottom"].values, float)
    if np.unique(tops[np.isfinite(tops)]).size < 2 or np.unique(bots[np.isfinite(bots)]).size < 2:
        name = grid_replay if isinstance(grid_replay, (str, os.PathLike)) else "the replay"
        raise ConfigError(f"{name} is not a density grid; replay with --density-grid START:STOP:STEP")
    keep = np.isfinite(tops) & np.isfinite(bots)
    T = np.asarray(rep["surface_temperature"].values[keep], np.float32)
    return run_ds, inversion.ForwardModel(T, tops[keep], bots[keep], rep["time"].values)


def observation_design(
    run: Union[Dataset, PathLike],
    grid_replay: Union[Dataset, PathLike],
    facet: int,
    *,
    instrument: str = "diviner_ch7",
    dwell_s: Sequence[float] = (1.0, 10.0, 100.0),
    local_times: Optional[int] = None,
    truth_kg_m3: tuple = (800.0, 1100.0),
    loose_bottom_kg_m3: float = 1500.0,
    refine: int = 4,
    natural_scatter_K: Optional[float] = None,
    offset_K: float = 0.0,
    model_error_K: Union[str, float] = "auto",
) -> dict:
    """Expected posterior width of an observation design on one facet (observation design, issue 23).

    The expectation is the posterior of the noiseless data of ``truth_kg_m3``
    (:func:`crater_thermal.inversion.expected_width`): which local times and dwells make the inversion
    informative, before observing.

    Parameters
    ----------
    run, grid_replay : Dataset or path-like
        A run and its density-grid replay.
    facet : int
        The facet observed.
    instrument : str
        Preset channel (``diviner_ch7``, ``diviner_ch8``, ``diviner_ch9``, ``microbolometer``).
    dwell_s : sequence of float [s]
        Dwell of each sample (the white noise averages over it down to the 1/f floor).
    local_times : int, optional
        None: one design per night sample of the facet (a single sample at that time of night: width versus
        time of night). An integer k: one design of k samples spread evenly over the facet's night samples.
        Night samples before the facet's first lit sample (a night that began before the run: no known
        sunset) are left out, unless the facet is never lit in the run.
    truth_kg_m3 : (top, bottom) [kg m-3]
        The profile assumed under the footprint (default: the thesis's loose 800/1100).
    loose_bottom_kg_m3 : float [kg m-3]
        Threshold of the expected P(loose).
    refine, natural_scatter_K, offset_K, model_error_K :
        As :func:`invert`.

    Returns
    -------
    dict
        ``time`` (n_design,) datetime64 (the single sample's time, or the first of k), ``hours_after_sunset``
        (n_design,) [h], ``dwell_s`` (n_dwell,) [s] and, each (n_design, n_dwell), ``sd_top_kg_m3``,
        ``sd_bottom_kg_m3`` [kg m-3], ``correlation``, ``p_loose`` [-]; ``prior_sd_kg_m3`` (2,),
        ``prior_p_loose``, ``truth_kg_m3``, ``instrument``, ``facet``.
    """
    import numpy as np

    from crater_thermal import instrument as ins
    from crater_thermal import inversion

    run_ds, fm = _forward_model(run, grid_replay)
    nf = fm.n_facets
    if isinstance(facet, bool) or int(facet) != facet or not 0 <= int(facet) < nf:
        raise ConfigError(f"facet={facet} is not a facet of the run (0..{nf - 1})")
    facet = int(facet)
    sun = np.asarray(run_ds["solar_incident"].values[:, facet], float)
    night = np.flatnonzero(sun <= 0.0)
    if night.size == 0:
        raise ConfigError(f"facet {facet} has no night sample in the run (solar_incident > 0 at every time)")
    # hours since the last lit sample; a night that began before the run has no known sunset: left out
    # unless the facet is never lit in the run (then hours since the run's start)
    lit = np.flatnonzero(sun > 0.0)
    t_s = (fm.times - fm.times[0]).astype(np.int64) / 1e9
    if lit.size:
        night = night[night > lit[0]]
        if night.size == 0:
            raise ConfigError(f"facet {facet} has no night sample after a sunset in the run")
    before = np.searchsorted(lit, night) - 1
    since = np.where(before >= 0, t_s[night] - t_s[lit[np.maximum(before, 0)]], t_s[night] - t_s[0])
    if local_times is None:
        designs = [fm.times[[k]] for k in night]
        first = night
    else:
        if int(local_times) < 1:
            raise ConfigError(f"local_times={local_times} must be >= 1")
        pick = night[np.linspace(0, night.size - 1, int(local_times)).round().astype(int)]
        designs, first = [fm.times[pick]], pick[:1]
    scatter = ins.NATURAL_SCATTER_K if natural_scatter_K is None else float(natural_scatter_K)
    out = inversion.expected_width(
        fm,
        facet,
        designs,
        dwell_s,
        instrument,
        truth_kg_m3=tuple(truth_kg_m3),
        refine=refine,
        natural_scatter_K=scatter,
        offset_K=offset_K,
        loose_bottom_kg_m3=loose_bottom_kg_m3,
        model_error_K=model_error_K,
    )
    out["time"] = fm.times[first]
    out["hours_after_sunset"] = since[np.searchsorted(night, first)] / 3600.0
    out["instrument"] = instrument
    out["facet"] = facet
    return out


def invert(
    run: PathLike,
    grid_replay: PathLike,
    observations: PathLike,
    *,
    instrument: Optional[str] = None,
    loose_bottom_kg_m3: float = 1500.0,
    prior: Any = "uniform",
    refine: int = 4,
    natural_scatter_K: Optional[float] = None,
    offset_K: float = 0.0,
    model_error_K: Union[str, float] = "auto",
    output: Optional[PathLike] = None,
    overwrite: bool = False,
    max_offset_m: Optional[float] = None,
):
    """Posterior over (top, bottom) density per footprint from measured brightness temperatures.

    Parameters
    ----------
    run, grid_replay : path-like
        The run and a density-grid replay made from it (>= 2 distinct top and bottom densities).
    observations : path-like
        Observation table, CSV or netCDF (:func:`crater_thermal.io.read_observations`).
    instrument : str, optional
        Instrument preset (e.g. ``"diviner_ch7"``); default: the table's, else ``"diviner_ch7"``.
    loose_bottom_kg_m3 : float [kg m-3]
        Threshold of ``p_loose``: bottom density below it.
    prior : ``"uniform"``, (n_top, n_bottom) array, or path-like
        Prior over the refined (top, bottom) nodes: uniform in density with top <= bottom inside the
        grid, non-negative weights (:func:`crater_thermal.inversion.invert`), or a netCDF file with
        ``prior(top, bottom)`` on those nodes (:func:`crater_thermal.io.read_prior`).
    refine : int
        Posterior nodes per grid step (4: a 100 kg m-3 grid gives 25 kg m-3 nodes).
    natural_scatter_K : float [K], optional
        Natural scatter of a footprint, shared by its samples (default: the instrument model's 0.94 K).
    offset_K : float [K]
        1-sigma calibration offset (at the instrument's reference temperature), shared by a footprint's
        samples and marginalized; 0: none.
    model_error_K : ``"auto"`` or float [K]
        Interpolation (model) error between grid densities in the likelihood: ``"auto"`` estimates it from
        the grid (leave one node out, :meth:`crater_thermal.inversion.ForwardModel.model_error_levers`),
        a number is a white 1-sigma error per sample [K], 0 takes the interpolation as exact.
    output : path-like, optional
        Write the posterior there (netCDF, atomically); then the written dataset is returned.
    overwrite : bool
        Replace an existing ``output``.
    max_offset_m : float [m], optional
        Farthest an ``x_m``/``y_m`` position may lie from its nearest facet centroid
        (default: twice the square root of the largest facet area).

    Returns
    -------
    crater_thermal.inversion.Posterior, or xarray.Dataset when ``output`` is given.
    """
    import numpy as np

    from crater_thermal import inversion

    if output is not None:
        io.check_output(output, overwrite, inputs=(run, grid_replay, observations))
    run_ds, fm = _forward_model(run, grid_replay)
    cols = io.read_observations(observations)
    facet, weight = cols["facet"], None
    if facet is None:
        from scipy.spatial import cKDTree

        c = np.asarray(run_ds["centroid"].values, float)[:, :2]
        area = np.asarray(run_ds["area"].values, float)
        tree = cKDTree(c)
        xy = np.column_stack([cols["x_m"], cols["y_m"]])
        if np.any(~np.isfinite(xy)):
            i = int(np.flatnonzero(~np.isfinite(xy).all(axis=1))[0])
            raise ConfigError(f"observations: sample {i} has no finite x_m, y_m position [m]")
        dist, facet = tree.query(xy)
        limit = max_offset_m if max_offset_m is not None else 2.0 * float(np.sqrt(np.max(area)))
        if np.any(dist > limit):
            i = int(np.flatnonzero(dist > limit)[0])
            raise ConfigError(
                f"observations: sample {i} at x={xy[i, 0]:g} m, y={xy[i, 1]:g} m is {dist[i]:.0f} m from the mesh "
                f"(limit {limit:.0f} m); give positions in the mesh frame (the run's centroid x, y)"
            )
        radius = cols.get("radius_m")
        if radius is not None:
            if np.any(~(np.isfinite(radius) & (radius >= 0))):
                i = int(np.flatnonzero(~(np.isfinite(radius) & (radius >= 0)))[0])
                raise ConfigError(f"observations: radius_m={radius[i]} of sample {i} must be >= 0 m")
            # footprint mixing: the facets whose centroids lie within the radius, weighted by area, the
            # nearest (centre) facet first and always included
            groups = [
                [int(facet[i])] + [g for g in members if g != facet[i]]
                for i, members in enumerate(tree.query_ball_point(xy, radius))
            ]
            k = max(len(g) for g in groups)
            F = np.repeat(np.asarray(facet, np.int64)[:, None], k, axis=1)
            weight = np.zeros((len(groups), k))
            for i, g in enumerate(groups):
                F[i, : len(g)] = g
                weight[i, : len(g)] = area[g] / area[g].sum()
            facet = F
    centre = facet if np.ndim(facet) == 1 else facet[:, 0]
    footprint = cols["footprint"] if cols["footprint"] is not None else centre
    obs = inversion.ObservationTable(
        time=cols["time"],
        facet=facet,
        footprint=footprint,
        T_b_K=cols["T_b_K"],
        sigma_K=cols["sigma_K"],
        dwell_s=cols["dwell_s"],
        instrument=instrument or cols["instrument"] or "diviner_ch7",
        facet_weight=weight,
    )
    from crater_thermal import instrument as ins

    scatter = ins.NATURAL_SCATTER_K if natural_scatter_K is None else float(natural_scatter_K)
    prior_note = "uniform in (top, bottom) density on the refined grid nodes with top <= bottom"
    if isinstance(prior, (str, os.PathLike)) and str(prior) != "uniform":
        weights, p_top, p_bottom = io.read_prior(prior)
        ta, ba = fm.density_axes(refine)
        if (
            p_top.shape != ta.shape
            or p_bottom.shape != ba.shape
            or not (np.allclose(p_top, ta) and np.allclose(p_bottom, ba))
        ):
            raise ConfigError(
                f"prior {prior}: its nodes ({p_top.size} top x {p_bottom.size} bottom) are not this grid's refined "
                f"nodes ({ta.size} x {ba.size}, refine={refine}); write it on those"
            )
        prior_note = f"from {prior} (weights on the refined nodes, zero outside the grid's triangle)"
        prior = weights
    elif not isinstance(prior, str):
        prior_note = "user weights on the refined (top, bottom) nodes (the file's prior variable)"
    post = inversion.invert(
        fm,
        obs,
        obs.instrument,
        prior=prior,
        loose_bottom_kg_m3=loose_bottom_kg_m3,
        refine=refine,
        natural_scatter_K=scatter,
        offset_K=offset_K,
        model_error_K=model_error_K,
    )
    if output is None:
        return post
    attrs = {
        "prior": prior_note,
        "instrument": obs.instrument,
        "refine": int(refine),
        "natural_scatter_K": scatter,
        "offset_K": float(offset_K),
        "model_error": (
            "auto: density-interpolation error estimated from the grid, leave one node out (each interior node "
            "interpolated from its neighbours at double spacing along top, bottom and the diagonal, the residual "
            "scaled by 1/4 to the grid's spacing; covariance twice the sum of the mean outer products over the "
            "nodes, correlated over a footprint's samples); variable model_error_K: its rms 1-sigma per footprint"
            if isinstance(model_error_K, str)
            else f"{float(model_error_K):g} K white (per sample) 1-sigma added to the noise"
        ),
        "noise_model": "white NETD(T)^2 (1/n + t_int/knee) per sample (or sigma_K); natural scatter, calibration "
        "offset and gain shared by a footprint's samples, marginalized (crater_thermal.inversion)",
        "run": str(run),
        "grid_replay": str(grid_replay),
        "observations": str(observations),
    }
    mh = run_ds.attrs.get("mesh_hash")
    if mh is not None:
        attrs["mesh_hash"] = str(mh)
    fac = np.asarray(obs.facet)[:, 0]  # each sample's centre facet (mixing: the nearest to its position)
    fp_facet = np.full(len(post.footprint), -1, np.int64)
    for i, f in enumerate(post.footprint):
        rows = obs.footprint == f
        if np.unique(fac[rows]).size == 1:
            fp_facet[i] = fac[rows][0]
    io.write_posterior(post, output, overwrite=overwrite, attrs=attrs, footprint_facet=fp_facet)
    return io.open_written(output)
