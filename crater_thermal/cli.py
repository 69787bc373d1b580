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

mesh_app = typer.Typer(no_args_is_help=True, help="Make crater meshes (idealized Table 7.1 crater, Ingersoll bowl).")
app.add_typer(mesh_app, name="mesh")


@mesh_app.command("crater")
def mesh_crater(
    diameter_km: float = typer.Option(10.0, "--diameter-km", help="Rim diameter [km], (0, 15]."),
    facets: int = typer.Option(502, "--facets", help="Exact number of facets (thesis: 502)."),
    surround_km: float = typer.Option(0.0, "--surround-km", help="Flat plain ring beyond the rim flank [km]."),
    wall: str = typer.Option("thesis", "--wall", help="Wall circle: 'thesis' (centre on axis) or 'tangent' (tangent to floor)."),
    output: Path = typer.Option(..., "-o", "--output", help="Output mesh (.ply, .obj, .stl)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output."),
) -> None:
    """Idealized simple crater (thesis Table 7.1) as a triangle mesh."""
    from crater_thermal import geometry

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

    m = geometry.bowl_mesh(depth_to_diameter=depth_to_diameter, n_facets=facets, diameter_m=diameter_m)
    geometry.save_mesh(m, output, overwrite=overwrite)
    typer.echo(f"wrote {output}: {m.n_facets} facets, hash {m.hash}")



# ---------------------------------------------------------------- steady (radiosity)


# ---------------------------------------------------------------- run / replay (simulate)


# ---------------------------------------------------------------- sweep


# ---------------------------------------------------------------- report / show


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
