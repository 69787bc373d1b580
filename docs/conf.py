"""Sphinx configuration of the crater_thermal documentation.

Built by ``make docs`` (and in ``make test``) with ``sphinx-build -W --keep-going -n -E``: every warning,
including an unresolved cross-reference, fails the build. Pages are MyST Markdown; the API reference is
autodoc of the numpy-style docstrings (numpydoc). Two local extensions in ``_ext/``: ``generated`` writes
the CLI, case-key and module-list pages from the typer app, the case schema and the import contract
before the pages are read; ``docstrings`` reads the docstrings' plain-text habits (``|x|``, short
underlines) as they are meant and resolves short references. Nothing is executed beyond imports: the
worked examples in ``examples/`` are run by ``tests/test_docs_examples.py``, not by the build.
"""

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))

from crater_thermal import __version__  # noqa: E402  (installed by `make install`)

project = "crater_thermal"
author = "the crater_thermal authors"
copyright = "the crater_thermal authors, BSD-3-Clause"
version = release = __version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "numpydoc",
    "generated",
    "docstrings",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "_generated"]
templates_path = []

# MyST: heading anchors for links such as [validation](validation.md#conduction), tables, definition lists.
myst_heading_anchors = 3
myst_enable_extensions = ["deflist", "colon_fence"]

# autodoc + numpydoc. Every public member, documented or not, also where a module's __all__ is shorter
# (docstrings refer to constants outside it). Types in docstrings stay text ("(n_facets, 3) float [m]" is a
# shape and a unit, not a class to link); signatures keep their annotations.
autodoc_default_options = {
    "members": True,
    "member-order": "bysource",
    "ignore-module-all": True,
    "undoc-members": True,
}
autodoc_typehints = "signature"
autodoc_preserve_defaults = True
autodoc_class_signature = "separated"
numpydoc_show_class_members = False
numpydoc_xref_param_type = False
numpydoc_class_members_toctree = False

# Nitpicky (-n): every cross-reference must resolve, except to third-party and standard-library objects
# (no intersphinx: the build reads nothing from the network).
nitpicky = True
_THIRD_PARTY = "numpy|np|xarray|xr|scipy|trimesh|skyfield|matplotlib|pyproj|rasterio|dask|distributed|typer|click"
_STDLIB = "pathlib|os|typing|collections|datetime|contextlib|concurrent|threading|enum"
nitpick_ignore_regex = [
    (r"py:.*", rf"({_THIRD_PARTY}|{_STDLIB})(\..*)?"),
    # bare names of those classes in annotations ("Path", "ndarray", ...)
    (r"py:(class|obj)", r"(Path|PathLike|Dataset|DataArray|ndarray|Callable|Iterator|Iterable|Any|Mapping|Sequence)"),
]

html_theme = "furo"
html_title = f"crater_thermal {release}"
html_static_path = []
html_show_sourcelink = False
