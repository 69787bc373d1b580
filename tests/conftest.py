import os
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

REPO = Path(__file__).resolve().parents[1]
SHARED_EPHEMERIS = REPO.parent / "shared" / "ephemeris"


@pytest.fixture
def repo_root() -> Path:
    return REPO
