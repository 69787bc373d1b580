import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
# A cache of view factors and horizon maps of this test session only (CLI subprocesses inherit it): the
# tests never read maps another checkout or code version wrote into the user's ~/.cache, nor fill it.
if "CRATER_THERMAL_CACHE" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="crater_thermal_tests_")
    os.environ["CRATER_THERMAL_CACHE"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)

REPO = Path(__file__).resolve().parents[1]
SHARED_EPHEMERIS = REPO.parent / "shared" / "ephemeris"


@pytest.fixture
def repo_root() -> Path:
    return REPO
