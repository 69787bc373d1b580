"""Tests of crater_thermal.viz: off-screen screenshots and animations of a synthetic crater."""

import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from crater_thermal import viz
from crater_thermal.errors import ConfigError, OutputExistsError

from synthetic import make_replay, make_run

pytest.importorskip("pyvista")

ENV = {
    **os.environ,
    "PYTHONPATH": str(viz.Path(viz.__file__).resolve().parents[1]),
    "VTK_DEFAULT_OPENGL_WINDOW": os.environ.get("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow"),
}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("viz")
    run = make_run(lat_deg=-86.0, n_lunar_days=1.0, n_rings=8)
    run.to_netcdf(d / "run.nc")
    make_replay(run, grid=False).to_netcdf(d / "replay.nc")
    return d


def _mesh_pixels(path):
    img = np.asarray(Image.open(path).convert("RGB"))
    return np.any(img < 250, axis=2).mean()  # background is white


def test_screenshot_shows_the_mesh(files, tmp_path):
    res = viz.show(files / "run.nc", time="2019-01-03T05:00", screenshot=tmp_path / "t.png", progress=False)
    assert res["screenshot"] == str(tmp_path / "t.png")
    assert res["time"].startswith("2019-01-03T04:00") or res["time"].startswith("2019-01-03T08:00")
    # the crater fills a good part of the 1024x768 view (measured ~45%); 10% means it was drawn at all
    assert _mesh_pixels(tmp_path / "t.png") > 0.10


def test_difference_and_flux_screenshots(files, tmp_path):
    viz.show(files / "run.nc", profile="800/1100", replay=files / "replay.nc", screenshot=tmp_path / "d.png")
    viz.show(files / "run.nc", var="solar_incident", screenshot=tmp_path / "f.png")
    for p in ("d.png", "f.png"):
        assert _mesh_pixels(tmp_path / p) > 0.10


def test_gif_animation(files, tmp_path):
    res = viz.show(files / "run.nc", animate=tmp_path / "a.gif", max_frames=3, progress=False)
    assert res["n_frames"] == 3
    with Image.open(tmp_path / "a.gif") as im:
        assert im.n_frames == 3


def test_bad_arguments(files, tmp_path):
    run = files / "run.nc"
    with pytest.raises(ConfigError, match="var="):
        viz.show(run, var="albedo", screenshot=tmp_path / "x.png")
    with pytest.raises(ConfigError, match="out of range"):
        viz.show(run, time="2031-01-01T00:00", screenshot=tmp_path / "x.png")
    with pytest.raises(ConfigError, match="ISO"):
        viz.show(run, time="yesterday", screenshot=tmp_path / "x.png")
    with pytest.raises(ConfigError, match="without a replay"):
        viz.show(run, profile="800/1100", screenshot=tmp_path / "x.png")
    with pytest.raises(ConfigError, match="allowed"):
        viz.show(run, profile="999/999", replay=files / "replay.nc", screenshot=tmp_path / "x.png")
    with pytest.raises(ConfigError, match="gif"):
        viz.show(run, animate=tmp_path / "x.avi")
    (tmp_path / "exists.png").write_bytes(b"x")
    with pytest.raises(OutputExistsError):
        viz.show(run, screenshot=tmp_path / "exists.png")


def test_cli_show(files, tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "crater_thermal",
            "show",
            str(files / "run.nc"),
            "--screenshot",
            str(tmp_path / "c.png"),
        ],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert _mesh_pixels(tmp_path / "c.png") > 0.10
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "crater_thermal",
            "show",
            str(files / "run.nc"),
            "--var",
            "nope",
            "--screenshot",
            str(tmp_path / "n.png"),
        ],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
    )
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "var=" in bad.stderr


def test_mp4_animation_through_imageio_ffmpeg(files, tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    res = viz.show(files / "run.nc", animate=tmp_path / "a.mp4", max_frames=3, fps=5.0, progress=False)
    assert res["n_frames"] == 3 and res["animation"] == str(tmp_path / "a.mp4")
    assert (tmp_path / "a.mp4").read_bytes()[4:8] == b"ftyp"  # an ISO-BMFF (MP4) container
    n_frames, _ = imageio_ffmpeg.count_frames_and_secs(str(tmp_path / "a.mp4"))
    assert n_frames == 3
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left
