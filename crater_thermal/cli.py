"""Command-line interface (typer). ``crater-thermal --help`` lists the commands.

Exit codes, never a traceback:

* 2 (``error: ...``, one line): a problem with the input, any
  :class:`~crater_thermal.errors.CraterThermalError` (bad value, mesh, flux file, existing output,
  missing optional extra), a usage error, or an operating-system refusal (permission, disk full);
* 3 (``internal error: ...``, one line asking for a bug report): an
  :class:`~crater_thermal.errors.InternalError` (including a failed solver) or any other unexpected
  exception; ``CRATER_THERMAL_TRACEBACK=1`` shows the traceback instead;
* 130 / 143 (``error: interrupted (SIGINT|SIGTERM) ...``, one line): stopped by Ctrl-C or SIGTERM; no
  output is damaged, and where a checkpoint is kept the line says how to resume. A signal that arrives
  after the command's output was renamed into place (only its clean-up was left) says so: that output is
  complete.

Help text is printed as plain text (no rich markup), so units in brackets (``[km]``) are shown as written.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import List, Optional

import typer

from crater_thermal.errors import CraterThermalError, InternalError, Interrupted, note_interrupt

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
    help="Thermal environment of lunar polar craters: meshes, fluxes, temperatures, reports.",
)


def _print_version(value: bool) -> None:
    if value:
        from crater_thermal._version import __version__

        typer.echo(f"crater-thermal {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """Thermal environment of lunar polar craters."""


def fail(message: str) -> None:
    """Print a one-line error and exit with code 2."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=2)


#: The outputs of the running command with what they were before it (see :func:`_watch`).
_WATCHED: list = []


def _identity(path: Path):
    """What tells a replaced file from the one before: (inode, mtime [ns], size), or None when absent."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_ino, st.st_mtime_ns, st.st_size)


def _watch(*paths) -> None:
    """Note the outputs a command writes, as they are before it, so that an interruption that arrives after
    one was renamed into place (every writer renames a finished temporary) does not claim nothing was written."""
    _WATCHED.extend((Path(p), _identity(Path(p))) for p in paths)


def _written_outputs() -> list:
    """The watched outputs the command has replaced or created (each complete: writes are atomic renames)."""
    return [str(p) for p, before in _WATCHED if (now := _identity(p)) is not None and now != before]


@app.command()
def version() -> None:
    """Print the crater_thermal version."""
    from crater_thermal._version import __version__

    typer.echo(__version__)


# ---------------------------------------------------------------- mesh (geometry)

mesh_app = typer.Typer(
    no_args_is_help=True, rich_markup_mode=None, help="Make crater meshes (idealized Table 7.1 crater, Ingersoll bowl)."
)
app.add_typer(mesh_app, name="mesh")


@mesh_app.command("crater")
def mesh_crater(
    diameter_km: float = typer.Option(10.0, "--diameter-km", help="Rim diameter [km], (0, 15]."),
    facets: int = typer.Option(502, "--facets", help="Exact number of facets (thesis: 502)."),
    surround_km: float = typer.Option(0.0, "--surround-km", help="Flat plain ring beyond the rim flank [km]."),
    wall: str = typer.Option(
        "thesis", "--wall", help="Wall circle: 'thesis' (centre on axis) or 'tangent' (tangent to floor)."
    ),
    output: Path = typer.Option(..., "-o", "--output", help="Output mesh (.ply, .obj, .stl)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output."),
) -> None:
    """Idealized simple crater (thesis Table 7.1) as a triangle mesh."""
    from crater_thermal import geometry

    _watch(output)
    m = geometry.crater_mesh(diameter_km=diameter_km, n_facets=facets, surround_km=surround_km, wall=wall)
    geometry.save_mesh(m, output, overwrite=overwrite)
    typer.echo(f"wrote {output}: {m.n_facets} facets, hash {m.hash}")


@mesh_app.command("bowl")
def mesh_bowl(
    depth_to_diameter: float = typer.Option(0.2, "--depth-to-diameter", help="Depth / diameter, (0, 0.5]."),
    facets: int = typer.Option(3000, "--facets", help="Exact number of facets."),
    diameter_m: float = typer.Option(1000.0, "--diameter-m", help="Rim diameter [m]."),
    output: Path = typer.Option(..., "-o", "--output", help="Output mesh (.ply, .obj, .stl)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output."),
) -> None:
    """Spherical-cap bowl (Ingersoll et al. 1992) as a triangle mesh."""
    from crater_thermal import geometry

    _watch(output)
    m = geometry.bowl_mesh(depth_to_diameter=depth_to_diameter, n_facets=facets, diameter_m=diameter_m)
    geometry.save_mesh(m, output, overwrite=overwrite)
    typer.echo(f"wrote {output}: {m.n_facets} facets, hash {m.hash}")


@mesh_app.command("dem")
def mesh_dem(
    dem: Path = typer.Argument(
        ..., help="DEM: GeoTIFF, PDS3 .LBL/.IMG (LOLA LDEM_*), GMT netCDF .grd, any GDAL raster, lunar CRS."
    ),
    center_lat: float = typer.Option(..., "--center-lat", help="Site centre, planetocentric latitude [deg]."),
    center_lon: float = typer.Option(..., "--center-lon", help="Site centre, east longitude [deg]."),
    radius_km: float = typer.Option(..., "--radius-km", help="Radius of the analysed (inner) region [km]."),
    resolution_m: Optional[float] = typer.Option(
        None, "--resolution-m", help="Facet edge in the inner region [m] (default: ~10k facets)."
    ),
    outer_radius_km: Optional[float] = typer.Option(
        None, "--outer-radius-km", help="Coarser ring for shadows/radiation out to this radius [km]."
    ),
    outer_resolution_m: Optional[float] = typer.Option(
        None, "--outer-resolution-m", help="Facet edge in the outer ring [m] (default 4x inner)."
    ),
    height_kind: str = typer.Option(
        "auto",
        "--height-kind",
        help="auto | height (above the sphere) | radius (from the Moon's centre) | tangent (curvature "
        "applied: z in a frame tangent at the projection's origin, as python-flux's LOLA .grd).",
    ),
    crs: Optional[str] = typer.Option(
        None,
        "--crs",
        help="CRS to use instead of the file's (none, or a wrong one): PROJ string, WKT, or a code such as "
        "IAU_2015:30135 (Moon south polar stereographic).",
    ),
    xy_units: Optional[str] = typer.Option(
        None, "--xy-units", help="m | km: unit of the DEM's x/y coordinates, whatever its CRS says."
    ),
    z_units: Optional[str] = typer.Option(
        None, "--z-units", help="m | km: unit of the DEM's values (heights), whatever its band says."
    ),
    max_facets: int = typer.Option(2_000_000, "--max-facets", help="Refuse larger sites (estimated up front)."),
    output: Path = typer.Option(..., "-o", "--output", help="Output mesh (.ply keeps the site metadata)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output."),
) -> None:
    """Mesh a site of a polar DEM: true 3-D positions in the centre's east/north/up frame [m].

    Reads GeoTIFF, PDS3, GMT/COARDS netCDF (.grd) and any GDAL raster; --crs, --xy-units, --z-units and
    --height-kind say what a file does not (e.g. a .grd in km without a CRS).
    """
    _watch(output)
    from crater_thermal import geometry, io, terrain
    from crater_thermal.errors import OutputExistsError

    if output.exists() and not overwrite:
        raise OutputExistsError(f"output {str(output)!r} exists; pass --overwrite to replace it")
    io.refuse_input_as_output(output, [dem])
    m = terrain.site_mesh(
        dem,
        center_lat,
        center_lon,
        radius_km,
        resolution_m=resolution_m,
        outer_radius_km=outer_radius_km,
        outer_resolution_m=outer_resolution_m,
        height_kind=height_kind,
        max_facets=max_facets,
        crs=crs,
        xy_units=xy_units,
        z_units=z_units,
    )
    geometry.save_mesh(m, output, overwrite=overwrite)
    typer.echo(
        f"wrote {output}: {m.n_facets} facets ({m.meta['n_inner']} inner), "
        f"{m.meta['resolution_m']:.4g} m, heights read as {m.meta['height_kind']!r}, hash {m.hash}"
    )


# ---------------------------------------------------------------- dem (synthetic sites)

dem_app = typer.Typer(
    no_args_is_help=True, rich_markup_mode=None, help="Digital elevation models: synthetic polar sites."
)
app.add_typer(dem_app, name="dem")


def _parse_crater(text: str) -> tuple:
    """'D_KM' or 'D_KM@X_KM,Y_KM' -> (diameter_km, x_km, y_km)."""
    from crater_thermal.errors import ConfigError

    try:
        d, _, at = text.partition("@")
        x, y = at.split(",") if at else ("0", "0")
        return float(d), float(x), float(y)
    except ValueError:
        raise ConfigError(f"--crater {text!r} must be D_KM or D_KM@X_KM,Y_KM (e.g. 5@2,-3)") from None


@dem_app.command("synth")
def dem_synth(
    lat_deg: float = typer.Option(..., "--lat-deg", help="Centre latitude [deg], |lat| >= 60."),
    lon_deg: float = typer.Option(0.0, "--lon-deg", help="Centre east longitude [deg]."),
    size_km: float = typer.Option(20.0, "--size-km", help="Side of the square raster [km]."),
    pixel_m: float = typer.Option(40.0, "--pixel-m", help="Pixel size [m] (polar stereographic, true at the pole)."),
    crater: List[str] = typer.Option(
        [],
        "--crater",
        help="D_KM[@X_KM,Y_KM]: idealized crater (Table 7.1), offset from the centre in map x, y [km]; its centre "
        "must lie on the raster and its rim cross it (it may reach past the edge). Repeatable.",
    ),
    roughness: float = typer.Option(0.0, "--roughness", help="RMS height of the self-affine background [m]."),
    hurst: float = typer.Option(0.9, "--hurst", help="Hurst exponent of the background, [0, 1]."),
    seed: int = typer.Option(0, "--seed", help="Random seed."),
    output: Path = typer.Option(
        ..., "-o", "--output", help="site.tif (GeoTIFF, float32 heights) or site.lbl (PDS3 int16 .IMG + .LBL)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing outputs."),
) -> None:
    """A synthetic polar site (rough terrain with craters) as a lunar polar-stereographic DEM."""
    _watch(output)
    from crater_thermal import terrain

    craters = [_parse_crater(c) for c in crater]
    z, tr, wkt = terrain.synthetic_heights(
        lat_deg, lon_deg, size_km, pixel_m, craters=craters, roughness_m=roughness, hurst=hurst, seed=seed
    )
    if output.suffix.lower() in (".lbl", ".img"):
        path = terrain.write_pds3(output, z, tr, pole="south" if lat_deg < 0 else "north", overwrite=overwrite)
    else:
        path = terrain.write_geotiff(output, z, tr, wkt, overwrite=overwrite)
    typer.echo(
        f"wrote {path}: {z.shape[1]} x {z.shape[0]} pixels of {pixel_m:g} m, heights "
        f"{float(z.min()):.0f} to {float(z.max()):.0f} m"
    )


# ---------------------------------------------------------------- steady (radiosity)


@app.command()
def steady(
    mesh: Path = typer.Argument(..., help="Mesh file (.ply, .obj, .stl) in the crater frame [m]."),
    sun_elevation_deg: float = typer.Option(..., "--sun-elevation-deg", help="Sun elevation [deg], [-90, 90]."),
    sun_azimuth_deg: float = typer.Option(
        180.0, "--sun-azimuth-deg", help="Sun azimuth [deg] from north, clockwise (east)."
    ),
    albedo: float = typer.Option(0.12, "--albedo", help="Albedo, [0, 1)."),
    emissivity: float = typer.Option(0.98, "--emissivity", help="Infrared emissivity, (0, 1]."),
    solar_constant: float = typer.Option(1361.0, "--solar-constant", help="Solar irradiance at 1 au [W m-2]."),
    point_sun: bool = typer.Option(False, "--point-sun", help="Point Sun instead of the limb-darkened disk."),
    limb_darkening: str = typer.Option(
        "linear", "--limb-darkening", help="uniform | linear | quadratic | neckel_labs."
    ),
    n_rings: int = typer.Option(4, "--sun-rings", help="Rings of the sampled solar disk (1 + 3n(n-1) patches)."),
    scattering: str = typer.Option("exact", "--scattering", help="exact | bounces."),
    n_bounces: int = typer.Option(3, "--bounces", help="Reflections kept with --scattering bounces."),
    view_factors: str = typer.Option(
        "auto",
        "--view-factors",
        help="auto | exact | compressed: exact sparse matrix or compressed operator (auto: by facet count, as "
        "a run chooses).",
    ),
    view_factor_tolerance: Optional[float] = typer.Option(
        None,
        "--view-factor-tolerance",
        help="Compressed operator: relative Frobenius error per far block, (0, 0.1] (default: a case file's).",
    ),
    solver: str = typer.Option(
        "auto",
        "--solver",
        help="auto | direct | iterative: LU, or fixed point (scattering) and GMRES (infrared) (auto: LU with "
        "exact view factors, iterative with the compressed operator).",
    ),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="Folder caching view factors by mesh hash."),
    flip: bool = typer.Option(False, "--flip", help="Reverse every facet's winding (normals pointing down)."),
    output: Path = typer.Option(..., "-o", "--output", help="Output netCDF file."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output."),
) -> None:
    """Radiative equilibrium (no conduction) of a mesh under a fixed Sun at 1 au."""
    _watch(output)
    from crater_thermal import steady as steady_mod

    path, res = steady_mod.steady_file(
        mesh,
        output,
        sun_elevation_deg,
        sun_azimuth_deg,
        albedo=albedo,
        emissivity=emissivity,
        solar_constant=solar_constant,
        point_sun=point_sun,
        limb_darkening=limb_darkening,
        n_rings=n_rings,
        method=scattering,
        n_bounces=n_bounces,
        view_factors=view_factors,
        tolerance=view_factor_tolerance,
        solver=solver,
        cache_dir=cache_dir,
        overwrite=overwrite,
        flip=flip,
    )
    T = res["surface_temperature"]
    typer.echo(f"wrote {path}: {T.size} facets, surface temperature {T.min():.2f} to {T.max():.2f} K")


# ---------------------------------------------------------------- run / replay (simulate)


_PROGRESS_HELP = (
    "Progress on stderr: a bar on a terminal, elsewhere (a log, a batch job) a line at most every 30 s with "
    "the time left. Default: on; --quiet (or CRATER_THERMAL_QUIET=1) for none."
)


@app.command()
def run(
    case: Path = typer.Argument(..., help="Case file (TOML), see cases/README.md."),
    output: Path = typer.Option(..., "-o", "--output", help="Run dataset to write (netCDF)."),
    resume: bool = typer.Option(False, "--resume", help="Continue from the checkpoint beside OUTPUT."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing OUTPUT."),
    progress: Optional[bool] = typer.Option(None, "--progress/--quiet", help=_PROGRESS_HELP),
    scheduler: Optional[str] = typer.Option(
        None,
        "--scheduler",
        help="dask scheduler address (tcp://host:8786): conduct the columns on its workers (each builds its rows "
        "of the view factors), coupled by waveform relaxation; OUTPUT's folder must be shared with them "
        "(docs/cluster.md).",
    ),
    workers: Optional[int] = typer.Option(
        None, "--workers", help="Instead of --scheduler: a local dask cluster of N one-thread processes."
    ),
    chunk_facets: Optional[int] = typer.Option(
        None,
        "--chunk-facets",
        help="With --scheduler/--workers: at most N facets per task (chunk); default one chunk per worker.",
    ),
) -> None:
    """Run a case: ephemeris -> direct sun -> scattering -> IR -> conduction, writing fluxes and temperatures."""
    from crater_thermal import api, runner
    from crater_thermal.errors import Interrupted
    from crater_thermal.progress import reporter

    _watch(output)
    try:
        api.run(
            case,
            output,
            resume=resume,
            overwrite=overwrite,
            progress=reporter(progress),
            scheduler=scheduler,
            workers=workers,
            chunk_facets=chunk_facets,
        ).close()
    except Interrupted as exc:
        ckpt = Path(runner.checkpoint_path(output))
        if ckpt.exists():
            where = f" --scheduler {scheduler}" if scheduler else (f" --workers {workers}" if workers else "")
            exc.hint = f"checkpoint {ckpt} kept: continue with `crater-thermal run {case} -o {output}{where} --resume`"
        raise
    typer.echo(f"wrote {output}")


@app.command()
def replay(
    flux: Path = typer.Argument(..., help="Run or flux dataset (netCDF) with solar_incident and ir_incident."),
    profile: List[str] = typer.Option(
        [], "--profile", help="Density profile: TOP/BOTTOM [kg m-3] (top 2 cm), 'rock', 'hayne2017'. Repeatable."
    ),
    density_grid: Optional[str] = typer.Option(
        None, "--density-grid", help="All top<=bottom pairs of START:STOP:STEP [kg m-3], e.g. 800:2000:100."
    ),
    initial_temperature: Optional[float] = typer.Option(
        None,
        "--initial-temperature",
        help="Uniform start [K], then the saved spin-up window once (thesis procedure), instead of the periodic "
        "steady state.",
    ),
    fixed_spinup: bool = typer.Option(
        False,
        "--fixed-spinup",
        help="Equilibrium-estimate start, then the saved spin-up window once (as a run with spinup = 'fixed').",
    ),
    property_set: Optional[str] = typer.Option(
        None, "--property-set", help="apollo (thesis) or hayne2017; default: the run's."
    ),
    allow_inverted: bool = typer.Option(False, "--allow-inverted", help="Allow top density > bottom density."),
    output: Path = typer.Option(..., "-o", "--output", help="Replay dataset to write (netCDF)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing OUTPUT."),
    progress: Optional[bool] = typer.Option(None, "--progress/--quiet", help=_PROGRESS_HELP),
    scheduler: Optional[str] = typer.Option(
        None,
        "--scheduler",
        help="dask scheduler address (tcp://host:8786): its workers solve the columns in chunks, reading FLUX at "
        "the same path; this process writes OUTPUT. See the docs' cluster page.",
    ),
    workers: Optional[int] = typer.Option(None, "--workers", help="A local dask cluster of N one-thread processes."),
    chunk_facets: int = typer.Option(2000, "--chunk-facets", help="With --scheduler/--workers: facets per task."),
    chunk_profiles: int = typer.Option(8, "--chunk-profiles", help="With --scheduler/--workers: profiles per task."),
    resume: bool = typer.Option(
        False, "--resume", help="With --scheduler/--workers: keep the finished chunks of an interrupted replay."
    ),
) -> None:
    """Replay saved fluxes against other density profiles (the IR stays the saved nominal one)."""
    _watch(output)
    from crater_thermal import api, cluster
    from crater_thermal.errors import Interrupted
    from crater_thermal.progress import reporter

    try:
        ds = api.replay(
            flux,
            profile,
            density_grid=density_grid,
            initial_temperature_K=initial_temperature,
            fixed_spinup=fixed_spinup,
            property_set=property_set,
            allow_inverted=allow_inverted,
            out=output,
            overwrite=overwrite,
            progress=reporter(progress),
            scheduler=scheduler,
            workers=workers,
            chunk_facets=chunk_facets,
            chunk_profiles=chunk_profiles,
            resume=resume,
        )
    except Interrupted as exc:
        folder = cluster.chunk_folder(output)
        if folder.exists():
            exc.hint = f"finished chunks kept in {folder}: run the same command with --resume to continue"
        raise
    if "replay_chunks" in ds.attrs:
        n, kept = int(ds.attrs["replay_chunks"]), int(ds.attrs["replay_chunks_resumed"])
        typer.echo(f"chunks: {n} ({kept} resumed, {n - kept} computed)")
    ds.close()
    typer.echo(f"wrote {output}")


# ---------------------------------------------------------------- sweep


@app.command()
def sweep(
    cases: List[Path] = typer.Argument(..., help="Case files (TOML)."),
    output: Path = typer.Option(..., "-o", "--output", help="Output folder: one sub-folder per case."),
    scheduler: Optional[str] = typer.Option(
        None, "--scheduler", help="dask.distributed scheduler address, e.g. tcp://host:8786."
    ),
    workers: Optional[int] = typer.Option(None, "--workers", help="Local processes (default: cores)."),
    progress: Optional[bool] = typer.Option(None, "--progress/--quiet", help=_PROGRESS_HELP),
) -> None:
    """Run many cases and their replays; a restarted sweep skips finished cases."""
    from crater_thermal import api
    from crater_thermal.errors import Interrupted

    try:
        results = api.run_sweep(cases, output, scheduler=scheduler, workers=workers, progress=progress)
    except Interrupted as exc:
        exc.hint = "run the same sweep command again to finish it (finished cases are skipped, runs resume)"
        raise
    for r in results:
        state = "skipped (already done)" if r["skipped"] else f"done in {r['seconds']:.1f} s"
        typer.echo(f"{Path(r['case']).stem}: {state}")


# ---------------------------------------------------------------- report / show


@app.command()
def report(
    run: Path = typer.Argument(..., help="Run dataset (crater-thermal run output), or a sweep's output folder."),
    replay: Optional[Path] = typer.Argument(None, help="Replay dataset made from RUN (omit for a sweep folder)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: report.html, figures/, summary.json."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing report.html."),
    instrument: List[str] = typer.Option(
        [],
        "--instrument",
        help="Preset channel (repeatable): diviner_ch7, diviner_ch8, diviner_ch9, microbolometer. Default: all.",
    ),
    band_um: Optional[str] = typer.Option(None, "--band-um", help="Add a user channel: LOW:HIGH band edges [um]."),
    netd_k: Optional[float] = typer.Option(None, "--netd-k", help="User channel: NETD of one integration [K]."),
    netd_at_k: float = typer.Option(300.0, "--netd-at-k", help="User channel: scene temperature of --netd-k [K]."),
    integration_s: float = typer.Option(0.128, "--integration-s", help="User channel: one integration [s]."),
    knee_s: float = typer.Option(60.0, "--knee-s", help="User channel: 1/f knee, dwell where averaging stops [s]."),
    gain_error: float = typer.Option(0.01, "--gain-error", help="User channel: relative 1-sigma gain error."),
    footprint_fraction: float = typer.Option(
        1.0, "--footprint-fraction", help="Loose fraction of the candidate footprint [0-1]."
    ),
    reference_footprints: int = typer.Option(
        1, "--reference-footprints", help="Nominal footprints averaged as the reference (m) [-]."
    ),
    candidate_footprints: int = typer.Option(
        1, "--candidate-footprints", help="Footprints spanned by the loose patch, averaged as the candidate (k) [-]."
    ),
    patch_area_m2: Optional[float] = typer.Option(
        None,
        "--patch-area-m2",
        help="Area of the loose patch [m2]; with --footprint-area-m2 it sets --candidate-footprints "
        "(whole footprints in it) and, below one footprint, the loose fraction.",
    ),
    footprint_area_m2: Optional[float] = typer.Option(
        None, "--footprint-area-m2", help="Area of one footprint [m2] (Diviner about 240 m x 480 m = 1.15e5 m2)."
    ),
    mode: str = typer.Option(
        "auto",
        "--mode",
        help="auto | stare | passes: a stare (dwell [s]) or repeated orbital passes (number of passes); "
        "auto: passes for orbital presets (Diviner), stare otherwise.",
    ),
    passes: int = typer.Option(
        100, "--passes", help="Orbital passes of the stated observation in pass mode (P_D maps, local time) [-]."
    ),
    pass_integration_s: Optional[float] = typer.Option(
        None,
        "--pass-integration-s",
        help="Integration on each footprint per pass [s] (default: the instrument's, Diviner 0.128 s).",
    ),
    natural_scatter_k: float = typer.Option(
        0.94, "--natural-scatter-k", help="Footprint-to-footprint scatter of true temperatures [K]."
    ),
    false_alarm: float = typer.Option(0.01, "--false-alarm", help="False-alarm rate of the one-sided test (0-1)."),
    no_snapshots: bool = typer.Option(False, "--no-snapshots", help="Skip the 3-D pyvista views."),
    night: str = typer.Option(
        "dark",
        "--night",
        help="Night: dark (default: no sunlight, direct or scattered above 1e-3 W m-2, on the facet for "
        "--min-dark-hours; a facet never dark that long uses its 10% least-lit samples without direct "
        "sunlight), facet (no direct sunlight for --min-dark-hours), centre (thesis: Sun below the crater "
        "centre's horizon), facet_and_centre.",
    ),
    min_dark_hours: float = typer.Option(24.0, "--min-dark-hours", help="Darkness before a facet's night [h]."),
    progress: Optional[bool] = typer.Option(None, "--progress/--quiet", help=_PROGRESS_HELP),
) -> None:
    """Report of a run and its replay: figures as thesis 7.4-7.9, detection statistics, report.html, summary.json."""
    _watch(out / "report.html")
    from crater_thermal import api
    from crater_thermal import instrument as ins
    from crater_thermal.errors import ConfigError

    insts = [ins.get_instrument(n) for n in instrument]
    if band_um is not None or netd_k is not None:
        if band_um is None or netd_k is None:
            raise ConfigError("a user channel needs both --band-um LOW:HIGH and --netd-k")
        try:
            lo, hi = (float(v) for v in band_um.split(":"))
        except ValueError:
            raise ConfigError(f"--band-um={band_um!r} must be LOW:HIGH in um, e.g. 8:14") from None
        insts.append(
            ins.custom_instrument(
                lo, hi, netd_k, netd_at_k, integration_s=integration_s, knee_s=knee_s, gain_error=gain_error
            )
        )
    obs = ins.Observation(
        footprint_fraction=footprint_fraction,
        reference_footprints=reference_footprints,
        natural_scatter_K=natural_scatter_k,
        false_alarm=false_alarm,
        candidate_footprints=candidate_footprints,
        patch_area_m2=patch_area_m2,
        footprint_area_m2=footprint_area_m2,
        mode=mode,
        passes=passes,
        pass_integration_s=pass_integration_s,
    )
    path = api.make_report(
        run,
        replay,
        out,
        overwrite=overwrite,
        progress=progress,
        instruments=insts or None,
        observation=obs,
        snapshots=not no_snapshots,
        night_definition=night,
        min_dark_hours=min_dark_hours,
    )
    typer.echo(str(path))
    typer.echo(_summary_text(path.parent / "summary.json"))


def _summary_text(summary_json: Path) -> str:
    """The headline of a report's summary.json, wrapped for a terminal."""
    import json

    from crater_thermal.errors import FluxFileError

    try:
        headline = json.loads(summary_json.read_text(encoding="utf-8"))["headline"]
    except (OSError, ValueError, KeyError, TypeError):
        raise FluxFileError(
            f"{summary_json} is not a crater_thermal summary with a headline (write one with crater-thermal report)"
        ) from None
    return _wrap(headline)


def _wrap(text: str) -> str:
    """A paragraph wrapped for a terminal (100 columns)."""
    import textwrap

    return textwrap.fill(text, width=100)


@app.command()
def summary(
    source: Path = typer.Argument(
        ..., help="A report folder (or its summary.json), or a run dataset (netCDF) with its replay as REPLAY."
    ),
    replay: Optional[Path] = typer.Argument(None, help="Replay dataset made from the run (when SOURCE is a run)."),
) -> None:
    """Print the answer: how much colder loose regolith is at night, where, when, and which instrument sees it."""
    from crater_thermal import api
    from crater_thermal.errors import ConfigError

    if source.is_dir():
        source = source / "summary.json"
    if source.suffix.lower() == ".json":
        typer.echo(_summary_text(source))
        return
    if replay is None:
        raise ConfigError(
            f"{source} is a run: give its replay too (crater-thermal summary RUN.nc REPLAY.nc), or a report folder"
        )
    typer.echo(_wrap(api.analyse(source, replay).headline))


@app.command()
def show(
    run: Path = typer.Argument(..., help="Run dataset."),
    time: Optional[str] = typer.Option(None, "--time", help="ISO UTC time (nearest sample); default: highest Sun."),
    var: str = typer.Option(
        "surface_temperature", "--var", help="surface_temperature | solar_incident | ir_incident | solar_direct."
    ),
    profile: Optional[str] = typer.Option(None, "--profile", help="Replayed profile label: show it minus nominal [K]."),
    replay: Optional[Path] = typer.Option(None, "--replay", help="Replay dataset (with --profile)."),
    screenshot: Optional[Path] = typer.Option(None, "--screenshot", help="Write a PNG (off-screen)."),
    animate: Optional[Path] = typer.Option(
        None, "--animate", help="Write an animation over time (.gif, or .mp4 with the viz extra)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing outputs."),
    max_frames: int = typer.Option(120, "--max-frames", help="Most frames in an animation."),
    exaggeration: float = typer.Option(1.0, "--exaggeration", help="Vertical exaggeration of the heights (0, 100]."),
) -> None:
    """3-D view of the crater coloured by a variable, with the Sun direction (pyvista)."""
    from crater_thermal.viz import show as _show

    res = _show(
        run,
        time=time,
        var=var,
        profile=profile,
        replay=replay,
        screenshot=screenshot,
        animate=animate,
        overwrite=overwrite,
        max_frames=max_frames,
        exaggeration=exaggeration,
    )
    for key in ("screenshot", "animation"):
        if res[key]:
            typer.echo(res[key])


@app.command()
def export(
    source: Path = typer.Argument(..., help="Run, replay or posterior (crater-thermal invert) dataset (netCDF)."),
    output: Path = typer.Option(..., "-o", "--output", help="GeoTIFF to write (.tif)."),
    variable: str = typer.Option(
        "surface_temperature",
        "--variable",
        help="Run: surface_temperature [K] | solar_incident | solar_direct | ir_incident | solar_absorbed "
        "[W m-2]. Replay: surface_temperature [K] | profile_minus_nominal [K]. Posterior (with --run): p_loose "
        "[-] | map_/mean_/sd_ top|bottom _kg_m3 [kg m-3], per footprint.",
    ),
    statistic: str = typer.Option(
        "night_median",
        "--statistic",
        help="Over time, per facet: night_median (per-facet night) | mean | min | max | at (with --time).",
    ),
    time: Optional[str] = typer.Option(None, "--time", help="ISO UTC time for --statistic at (nearest sample)."),
    profile: Optional[str] = typer.Option(
        None,
        "--profile",
        help="Replay profile: TOP/BOTTOM [kg m-3] or a label (default: nominal; loose 800/1100 for "
        "profile_minus_nominal, in [K]).",
    ),
    run: Optional[Path] = typer.Option(
        None,
        "--run",
        help="The run a replay or posterior was made from (needed for night_median of a replay and "
        "for a posterior's mesh).",
    ),
    pixel_m: Optional[float] = typer.Option(None, "--pixel-m", help="Pixel size [m]; default: the mean facet edge."),
    night: Optional[str] = typer.Option(
        None, "--night", help="Night definition for night_median, as report's --night; default: the report's."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing OUTPUT."),
) -> None:
    """Rasterize a per-facet quantity to a GeoTIFF (DEM's CRS, or a crater-centred lunar CRS) for QGIS."""
    _watch(output)
    from crater_thermal import api

    api.export_map(
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
    typer.echo(f"wrote {output}")


# ---------------------------------------------------------------- invert


@app.command()
def invert(
    run: Path = typer.Argument(..., help="Run dataset (crater-thermal run output)."),
    grid_replay: Path = typer.Argument(
        ..., help="Density-grid replay of RUN (crater-thermal replay RUN --density-grid START:STOP:STEP)."
    ),
    observations: Path = typer.Argument(
        ...,
        help="Observation table, CSV or netCDF: time (ISO UTC), facet or x_m/y_m [m, mesh frame], "
        "brightness_temperature_K [K], optional sigma_K [K], dwell_s [s], footprint, instrument, radius_m [m] "
        "(with x_m/y_m: footprint mixing).",
    ),
    output: Path = typer.Option(..., "-o", "--output", help="Posterior to write (netCDF)."),
    instrument: Optional[str] = typer.Option(
        None,
        "--instrument",
        help="Preset channel: diviner_ch7, diviner_ch8, diviner_ch9, microbolometer. Default: the table's "
        "instrument column, else diviner_ch7.",
    ),
    loose_below: float = typer.Option(
        1500.0, "--loose-below", help="P(loose) threshold: bottom-layer density below it [kg m-3]."
    ),
    refine: int = typer.Option(4, "--refine", help="Posterior nodes per grid step (4: 100 -> 25 kg m-3)."),
    prior: str = typer.Option(
        "uniform",
        "--prior",
        help="uniform (in top and bottom density [kg m-3], top <= bottom), or a netCDF file with prior(top, "
        "bottom) weights on the refined nodes (coordinates top_kg_m3, bottom_kg_m3; e.g. an edited posterior.nc).",
    ),
    natural_scatter: Optional[float] = typer.Option(
        None, "--natural-scatter-k", help="Natural scatter of a footprint [K] (default 0.94, the instrument model's)."
    ),
    offset_k: float = typer.Option(
        0.0,
        "--offset-k",
        help="1-sigma calibration offset [K] at the instrument's reference temperature, marginalized (default 0).",
    ),
    model_error: str = typer.Option(
        "auto",
        "--model-error-k",
        help="Interpolation error between grid densities [K]: auto (estimated from the grid, leave one node "
        "out, correlated over a footprint's samples), or a 1-sigma per sample in K (0: interpolation exact).",
    ),
    max_offset_m: Optional[float] = typer.Option(
        None, "--max-offset-m", help="Farthest an x_m/y_m position may lie from its facet [m] (default: 2 facet sizes)."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing OUTPUT."),
) -> None:
    """Posterior over (top, bottom) density per footprint from measured brightness temperatures.

    The prior is uniform in (top, bottom) density over the grid's refined nodes with top <= bottom (or
    --prior FILE). The
    posterior file holds, per footprint, the posterior mass on the nodes, its marginals, P(loose), MAP,
    mean, sd, the 90 % credible region and a sentence on the degeneracies.
    """
    _watch(output)
    from crater_thermal import api

    if model_error != "auto":
        from crater_thermal.errors import ConfigError

        try:
            model_error = float(model_error)
        except ValueError:
            raise ConfigError(f"--model-error-k {model_error}: give 'auto' or a number of kelvin (e.g. 0.05)") from None
    ds = api.invert(
        run,
        grid_replay,
        observations,
        instrument=instrument,
        loose_bottom_kg_m3=loose_below,
        refine=refine,
        prior=prior,
        natural_scatter_K=natural_scatter,
        offset_K=offset_k,
        model_error_K=model_error,
        output=output,
        overwrite=overwrite,
        max_offset_m=max_offset_m,
    )
    n = ds.sizes["footprint"]
    loose = int((ds["p_loose"].values > 0.5).sum())
    ds.close()
    typer.echo(f"wrote {output} ({n} footprints, {loose} with P(bottom < {loose_below:g} kg m-3) > 0.5)")


# ---------------------------------------------------------------- cache

cache_app = typer.Typer(
    no_args_is_help=True,
    rich_markup_mode=None,
    help="The cache of view factors and horizon maps ($CRATER_THERMAL_CACHE or ~/.cache/crater_thermal).",
)
app.add_typer(cache_app, name="cache")


def _size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return ""  # pragma: no cover


@cache_app.command("info")
def cache_info() -> None:
    """Where the cache is and what it holds (files and sizes per kind); deleting it is always safe."""
    from crater_thermal import cache

    i = cache.info()
    where = i["root"] + ("" if i["exists"] else " (not created yet)")
    typer.echo(f"cache {where}: {i['files']} files, {_size(i['bytes'])}")
    for kind, k in i["kinds"].items():
        typer.echo(f"  {kind}: {k['files']} files, {_size(k['bytes'])}")


@cache_app.command("clear")
def cache_clear(
    kind: Optional[str] = typer.Option(None, "--kind", help="Clear only this kind: viewfactors | horizons."),
) -> None:
    """Delete the cached entries (recomputed when next needed); nothing else in the folder is touched."""
    from crater_thermal import cache

    r = cache.clear(kind)
    typer.echo(f"removed {r['files']} files, {_size(r['bytes'])} from {cache.root()}")


# ---------------------------------------------------------------- entry point


def _install_signal_handlers() -> None:
    """SIGINT and SIGTERM raise :class:`~crater_thermal.errors.Interrupted` in the main thread, so that every
    writer cleans up (temporary files removed, locks released, existing outputs untouched). A second
    signal during that clean-up ends the process at once with the same exit code."""
    import signal

    def handler(signum, frame):
        if getattr(handler, "fired", False):
            print(f"error: interrupted again ({signal.Signals(signum).name}); exiting at once", file=sys.stderr)
            os._exit(128 + signum)
        handler.fired = True
        note_interrupt(signum)  # kept, in case C code swallows the raise below (errors.raise_if_interrupted)
        raise Interrupted(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            signal.signal(sig, handler)
        except (ValueError, OSError):  # not the main thread (an embedding program): leave its handlers
            pass


def _interrupted(code: int, name: str, hint: str = "") -> None:
    written = _written_outputs()
    if written:  # the signal came after the work: the output is whole, only the clean-up was cut short
        hint = f"{', '.join(written)} had been written in full before it (only the clean-up after was cut short)"
    tail = f"; {hint}" if hint else "; no output was written or changed"
    print(f"error: interrupted ({name}){tail}", file=sys.stderr)
    sys.exit(code)


def main(argv: Optional[List[str]] = None) -> None:
    """Console-script entry point."""
    import warnings

    from crater_thermal.progress import one_line_warning

    warnings.showwarning = one_line_warning
    _install_signal_handlers()
    try:
        rc = app(args=argv, standalone_mode=False)
    except Interrupted as exc:
        _interrupted(exc.exit_code, exc.signal_name, exc.hint)
    except CraterThermalError as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        sys.exit(2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):
        _interrupted(130, "SIGINT")
    except Exception as exc:
        if hasattr(exc, "show") and hasattr(exc, "exit_code"):  # usage errors from typer's bundled click
            exc.show()
            sys.exit(2)
        if isinstance(exc, OSError) and not isinstance(exc, InternalError):  # permission, disk full, ...
            where = f": {exc.filename}" if getattr(exc, "filename", None) else ""
            print(f"error: {exc.strerror or _one_line(exc)}{where}", file=sys.stderr)
            sys.exit(2)
        if os.environ.get("CRATER_THERMAL_TRACEBACK"):
            raise
        kind = "" if isinstance(exc, InternalError) else f"{type(exc).__name__}: "
        print(
            f"internal error: {kind}{_one_line(exc)} (a bug in crater_thermal, not in your input: please "
            "report it with the command line and its input files; CRATER_THERMAL_TRACEBACK=1 shows the "
            "traceback)",
            file=sys.stderr,
        )
        sys.exit(3)
    # typer returns the code of an Exit raised inside a command (its KeyboardInterrupt handler returns 130)
    if isinstance(rc, int) and not isinstance(rc, bool) and rc != 0:
        if rc == 130:
            _interrupted(130, "SIGINT")
        sys.exit(rc)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
