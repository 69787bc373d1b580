"""The version of crater_thermal (one place; the package, outputs and --version read it)."""

__version__ = "0.1.0"
