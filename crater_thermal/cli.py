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
