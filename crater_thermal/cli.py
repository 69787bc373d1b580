"""Command-line interface (typer). ``crater-thermal --help`` lists the commands.

Any :class:`~crater_thermal.errors.CraterThermalError` becomes a one-line
``error: ...`` on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import List, Optional

import typer

from crater_thermal.errors import CraterThermalError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Thermal environment of lunar polar craters: meshes, fluxes, temperatures, reports.",
)


@app.callback()
def _root() -> None:
    """Thermal environment of lunar polar craters."""


def fail(message: str) -> None:
    """Print a one-line error and exit with code 2."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=2)


@app.command()
def version() -> None:
    """Print the crater_thermal version."""
    from crater_thermal import __version__

    typer.echo(__version__)


# ---------------------------------------------------------------- mesh (geometry)


# ---------------------------------------------------------------- steady (radiosity)


# ---------------------------------------------------------------- run / replay (simulate)


# ---------------------------------------------------------------- sweep


# ---------------------------------------------------------------- report / show


@app.command()
def report(
    run: Path = typer.Argument(..., help="Run dataset (crater-thermal run output)."),
    replay: Path = typer.Argument(..., help="Replay dataset made from RUN."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: report.html, figures/, summary.json."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing report.html."),
    footprint_fraction: float = typer.Option(1.0, help="Pixel fraction of loose regolith (Eq. 8.2) [0-1]."),
    no_snapshots: bool = typer.Option(False, "--no-snapshots", help="Skip the 3-D pyvista views."),
    k_sigma: float = typer.Option(3.0, "--k-sigma", help="Detection threshold in units of NETD/sqrt(n)."),
    netd_ref_k: float = typer.Option(2.0, "--netd-ref-k", help="Detector NETD [K] at 50 K (Diviner ~2 K)."),
    scatter_in_quadrature: bool = typer.Option(False, "--scatter-in-quadrature",
                                               help="Stricter: add the 0.94 K natural scatter in quadrature."),
) -> None:
    """Figures (thesis Figs. 7.4-7.9), report.html and summary.json for a run and its replay."""
    from crater_thermal.analysis import Instrument
    from crater_thermal.report import make_report

    inst = Instrument(k_sigma=k_sigma, netd_ref_K=netd_ref_k, scatter_in_quadrature=scatter_in_quadrature)
    path = make_report(run, replay, out, overwrite=overwrite, footprint_fraction=footprint_fraction,
                       snapshots=not no_snapshots, instrument=inst)
    typer.echo(str(path))


@app.command()
def show(
    run: Path = typer.Argument(..., help="Run dataset."),
    time: Optional[str] = typer.Option(None, "--time", help="ISO UTC time (nearest sample); default: highest Sun."),
    var: str = typer.Option("surface_temperature", "--var",
                            help="surface_temperature | solar_incident | ir_incident | solar_direct."),
    profile: Optional[str] = typer.Option(None, "--profile", help="Replayed profile label: show it minus nominal [K]."),
    replay: Optional[Path] = typer.Option(None, "--replay", help="Replay dataset (with --profile)."),
    screenshot: Optional[Path] = typer.Option(None, "--screenshot", help="Write a PNG (off-screen)."),
    animate: Optional[Path] = typer.Option(None, "--animate", help="Write an animation over time (.gif; .mp4 needs imageio[ffmpeg])."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing outputs."),
    max_frames: int = typer.Option(120, "--max-frames", help="Most frames in an animation."),
) -> None:
    """3-D view of the crater coloured by a variable, with the Sun direction (pyvista)."""
    from crater_thermal.viz import show as _show

    res = _show(run, time=time, var=var, profile=profile, replay=replay, screenshot=screenshot,
                animate=animate, overwrite=overwrite, max_frames=max_frames)
    for key in ("screenshot", "animation"):
        if res[key]:
            typer.echo(res[key])


def main(argv: Optional[List[str]] = None) -> None:
    """Console-script entry point."""
    try:
        app(args=argv, standalone_mode=False)
    except CraterThermalError as exc:
        msg = " ".join(str(exc).split())
        print(f"error: {msg}", file=sys.stderr)
        sys.exit(2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)
    except Exception as exc:  # usage errors from typer's bundled click
        if hasattr(exc, "show") and hasattr(exc, "exit_code"):
            exc.show()
            sys.exit(2)
        raise
