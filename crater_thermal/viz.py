"""3-D views of a crater run with pyvista (the only pyvista importer; imported lazily).

:func:`show` colours the crater mesh by a variable at one time (temperature [K], a replayed profile
minus nominal [K], or a flux [W m-2]), with a colour bar titled with the unit, an arrow toward the
Sun, and the date in the title. It opens an interactive window when a display exists; otherwise
it renders off-screen (``pyvista.OFF_SCREEN``; on headless machines VTK can use Mesa EGL with
``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``).

Animations: GIF frames are written with Pillow; MP4 uses pyvista's ``open_movie`` through
imageio-ffmpeg (a wheel that carries its own ffmpeg binary; part of the ``viz`` extra). Without
pyvista (or imageio-ffmpeg for MP4) a one-line :class:`~crater_thermal.errors.MissingExtraError`
names the extra to install. Every file goes through :func:`crater_thermal.io.atomic_output`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from crater_thermal import analysis as an
from crater_thermal import io as ctio
from crater_thermal.errors import ConfigError
from crater_thermal.extras import missing_extra

#: Variables :func:`show` can colour by: name -> (label, unit).
VARIABLES = {
    "surface_temperature": ("Surface temperature", "K"),
    "solar_incident": ("Solar incident flux", "W m-2"),
    "ir_incident": ("IR incident flux", "W m-2"),
    "solar_direct": ("Direct solar flux", "W m-2"),
}


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _pyvista():
    """Import pyvista (the ``viz`` extra); render off-screen when there is no display."""
    if not _has_display():
        # headless: let VTK go straight to EGL instead of warning about a missing X server
        # (override with VTK_DEFAULT_OPENGL_WINDOW, e.g. vtkOSOpenGLRenderWindow for OSMesa builds)
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    try:
        import pyvista as pv
    except ImportError:
        raise missing_extra("pyvista", "viz", "3-D views") from None
    if not _has_display():
        pv.OFF_SCREEN = True
    return pv


def polydata(ds, exaggeration: float = 1.0):
    """pyvista PolyData of the run's mesh (``mesh_vertices`` [m], ``mesh_faces``), heights times
    ``exaggeration`` (vertical exaggeration about the site frame's z = 0)."""
    pv = _pyvista()
    v = np.array(ds["mesh_vertices"].values, dtype=float)
    v[:, 2] *= float(exaggeration)
    f = np.asarray(ds["mesh_faces"].values, dtype=np.int64)
    cells = np.hstack([np.full((len(f), 1), 3, dtype=np.int64), f]).ravel()
    return pv.PolyData(v, cells)


def site_exaggeration(ds) -> float:
    """A vertical exaggeration that makes a site's relief readable: 1 for craters and steep terrain; for a
    DEM site, enough to make the relief ~15 % of the horizontal extent, at most 10 (rounded)."""
    import json

    try:
        kind = json.loads(ds.attrs.get("mesh_meta", "{}")).get("kind")
    except ValueError:
        kind = None
    if kind != "dem":
        return 1.0
    v = np.asarray(ds["mesh_vertices"].values, dtype=float)
    extent = float(max(np.ptp(v[:, 0]), np.ptp(v[:, 1])))
    relief = float(np.ptp(v[:, 2]))
    if relief <= 0.0:
        return 1.0
    return float(np.clip(round(0.15 * extent / relief), 1.0, 10.0))


def _check_exaggeration(exaggeration) -> float:
    try:
        x = float(exaggeration)
    except (TypeError, ValueError):
        raise ConfigError(f"exaggeration={exaggeration!r} must be a number") from None
    if not (np.isfinite(x) and 0.0 < x <= 100.0):
        raise ConfigError(f"exaggeration={exaggeration!r} out of range (0, 100]")
    return x


def time_label(t) -> str:
    """ISO date-time to the minute, UTC."""
    return f"{np.datetime_as_string(np.datetime64(t, 'ns'), unit='m')} UTC"


def select_time(times, time: Optional[str], sun_direction=None) -> int:
    """Index of the sample nearest an ISO time; default: the highest Sun (if known), else the last.

    Raises
    ------
    ConfigError
        If ``time`` is not ISO or lies outside the run's span (by more than one step).
    """
    times = np.asarray(times).astype("datetime64[ns]")
    if time is None:
        if sun_direction is not None:
            return int(np.argmax(np.asarray(sun_direction)[:, 2]))
        return len(times) - 1
    try:
        t = np.datetime64(str(time).rstrip("Z"), "ns")
    except ValueError:
        raise ConfigError(f"time={time!r} is not an ISO date-time (e.g. 2019-01-05T12:00)") from None
    step = (times[1] - times[0]) if len(times) > 1 else np.timedelta64(0, "ns")
    if t < times[0] - step or t > times[-1] + step:
        raise ConfigError(f"time={time} out of range [{time_label(times[0])}, {time_label(times[-1])}]")
    return int(np.argmin(np.abs((times - t).astype(np.int64))))


def field(run, var: str = "surface_temperature", replay=None, profile: Optional[str] = None):
    """The (nt, nf) field to show, with its colour-bar title and a default colour map.

    With ``profile`` (and ``replay``), the field is that profile's surface temperature minus the
    nominal one [K]; otherwise ``run[var]``.
    """
    if profile is not None:
        if replay is None:
            raise ConfigError("profile given without a replay dataset (--replay REPLAY.nc)")
        if var != "surface_temperature":
            raise ConfigError(f"var={var!r} with a profile: only surface_temperature differences are shown")
        ctio.check_pair(run, replay)
        labels = an.profile_labels(replay)
        if profile not in labels:
            raise ConfigError(f"profile={profile!r} not in the replay; allowed: {', '.join(labels)}")
        vals = an.profile_temperature(replay, profile) - an.nominal_temperature(run, replay)
        return vals, f"{profile} - nominal [K]", "RdBu_r"
    if var not in VARIABLES:
        raise ConfigError(f"var={var!r} not allowed; allowed: {', '.join(VARIABLES)}")
    try:
        vals = np.asarray(run[var].values, float)
    except KeyError:
        raise ConfigError(f"var={var!r} is not in this run dataset") from None
    label, unit = VARIABLES[var]
    return vals, f"{label} [{unit}]", ("inferno" if unit == "K" else "viridis")


class _Scene:
    """A plotter holding the crater, a Sun arrow and a title; frames update values in place."""

    def __init__(
        self,
        run,
        scalar_title: str,
        cmap: str,
        clim: Tuple[float, float],
        window_size: Tuple[int, int] = (1024, 768),
        off_screen: bool = True,
        exaggeration: float = 1.0,
    ):
        pv = _pyvista()
        self.pv = pv
        self.exaggeration = _check_exaggeration(exaggeration)
        self.mesh = polydata(run, self.exaggeration)
        self.mesh.cell_data["values"] = np.zeros(self.mesh.n_cells)
        # outer shadow-only terrain of a DEM site (facets not analysed) is drawn grey
        self.outer = ~np.asarray(run["inner"].values).astype(bool) if "inner" in run else None
        self.p = pv.Plotter(off_screen=off_screen, window_size=list(window_size))
        self.p.set_background("white")
        self.p.add_mesh(
            self.mesh,
            scalars="values",
            cmap=cmap,
            clim=clim,
            show_edges=False,
            nan_color="lightgrey",
            scalar_bar_args=dict(
                title=scalar_title,
                color="black",
                vertical=True,
                position_x=0.85,
                position_y=0.15,
                height=0.7,
                width=0.06,
            ),
        )
        b = np.asarray(self.mesh.bounds, float)
        if self.outer is not None and self.outer.any() and not self.outer.all():
            # frame the analysed region, not the (much wider) outer ring
            pts = np.asarray(self.mesh.points)[np.asarray(run["mesh_faces"].values)[~self.outer].ravel()]
            b = np.ravel(np.column_stack([pts.min(axis=0), pts.max(axis=0)]))
        self.extent = float(max(b[1] - b[0], b[3] - b[2]))
        self.top = float(b[5])
        self.times = np.asarray(run["time"].values)
        self.sun = np.asarray(run["sun_direction"].values, float) if ctio.has_variable(run, "sun_direction") else None
        # look from the equator side, so the pole-side (Sun-facing) inner wall is in view
        lat = ctio.latitude_deg(run)
        self.p.view_vector((0.35, 1.0 if lat <= 0 else -1.0, 1.1), viewup=(0.0, 0.0, 1.0))
        self.p.reset_camera(bounds=list(b))
        self.p.camera.zoom(1.25)

    def update(self, values, i: int, title: str):
        values = np.array(values, float)
        if self.outer is not None and self.outer.any():
            values[self.outer] = np.nan
        self.mesh.cell_data["values"] = values
        if self.exaggeration != 1.0:
            title = f"{title}  (vertical x{self.exaggeration:g})"
        if self.sun is not None:
            s = self.sun[i]
            above = s[2] >= 0
            start = np.array([0.0, 0.0, self.top + 0.05 * self.extent])
            arrow = self.pv.Arrow(start=start, direction=s, scale=0.35 * self.extent)
            self.p.add_mesh(arrow, color="gold" if above else "gray", name="sun", show_scalar_bar=False)
            elev = np.degrees(np.arcsin(np.clip(s[2], -1, 1)))
            title = f"{title}\n{time_label(self.times[i])}   Sun elevation {elev:.2f} deg"
        else:
            title = f"{title}\n{time_label(self.times[i])}"
        self.p.add_text(title, position="upper_left", font_size=11, color="black", name="title")

    def image(self) -> np.ndarray:
        self.p.render()
        return np.asarray(self.p.screenshot(None, return_img=True))

    def close(self):
        self.p.close()


def snapshot(
    run,
    values,
    time_index: int,
    scalar_title: str,
    title: str,
    path,
    cmap: str = "inferno",
    clim: Optional[Tuple[float, float]] = None,
    window_size: Tuple[int, int] = (900, 700),
    exaggeration: float = 1.0,
    overwrite: bool = False,
) -> Path:
    """Render one off-screen view of per-facet ``values`` (nf,) and write it to ``path`` (PNG).

    Used by the report. ``exaggeration``: vertical exaggeration of the heights. The PNG is written
    through :func:`crater_thermal.io.atomic_output`; an existing ``path`` is refused unless
    ``overwrite``. Returns the path.
    """
    values = np.asarray(values, float)
    if clim is None:
        finite = values[np.isfinite(values)]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        clim = (lo, hi if hi > lo else lo + 1.0)
    scene = _Scene(run, scalar_title, cmap, clim, window_size, off_screen=True, exaggeration=exaggeration)
    try:
        scene.update(values, time_index, title)
        img = scene.image()
    finally:
        scene.close()
    from PIL import Image

    with ctio.atomic_output(path, overwrite) as tmp:
        Image.fromarray(img).save(tmp, format="PNG")
    return Path(path)


def _frame_indices(nt: int, max_frames: int) -> np.ndarray:
    if max_frames < 2:
        raise ConfigError(f"max_frames={max_frames} out of range [2, inf)")
    return np.unique(np.linspace(0, nt - 1, min(nt, max_frames)).round().astype(int))


def show(
    run_path,
    time: Optional[str] = None,
    var: str = "surface_temperature",
    profile: Optional[str] = None,
    replay=None,
    screenshot=None,
    animate=None,
    overwrite: bool = False,
    window_size: Tuple[int, int] = (1024, 768),
    max_frames: int = 120,
    fps: float = 10.0,
    progress: Optional[bool] = None,
    exaggeration: float = 1.0,
) -> dict:
    """Show the crater coloured by a variable, or write a screenshot / animation.

    Parameters
    ----------
    run_path : path or dataset
        Run dataset (``crater-thermal run`` output).
    time : str, optional
        ISO UTC time; the nearest sample is shown. Default: the sample with the highest Sun.
    var : str
        One of :data:`VARIABLES`: surface_temperature [K], solar_incident / ir_incident / solar_direct [W m-2].
    profile : str, optional
        A replayed profile label: show its surface temperature minus nominal [K] (needs ``replay``).
    replay : path or dataset, optional
        Replay dataset made from this run.
    screenshot : path, optional
        Write a PNG (off-screen).
    animate : path, optional
        Write an animation over time: ``.gif`` (Pillow) or ``.mp4`` (imageio-ffmpeg, ``viz`` extra).
    overwrite : bool
        Replace existing outputs.
    window_size : (int, int) [px]
    max_frames : int
        At most this many (evenly spaced) samples in an animation.
    fps : float [1/s]
        Animation frame rate.
    progress : bool, optional
        Progress bar for animations; default: only on a terminal.
    exaggeration : float
        Vertical exaggeration of the heights, (0, 100] (e.g. 3 for a DEM site's gentle relief).

    Returns
    -------
    dict with ``time`` (ISO of the shown sample), ``screenshot``, ``animation`` (paths or None), ``n_frames``.
    """
    inputs = [p for p in (run_path, replay) if isinstance(p, (str, os.PathLike))]
    for out in (screenshot, animate):
        if out:
            ctio.refuse_input_as_output(out, inputs)
    opened = []
    try:
        if isinstance(run_path, (str, os.PathLike)):
            run_path = ctio.open_run(run_path)
            opened.append(run_path)
        if isinstance(replay, (str, os.PathLike)):
            replay = ctio.open_replay(replay)
            opened.append(replay)
        return _show(
            run_path,
            time,
            var,
            profile,
            replay,
            screenshot,
            animate,
            overwrite,
            window_size,
            max_frames,
            fps,
            progress,
            exaggeration,
        )
    finally:
        for ds in opened:
            ds.close()


def _show(
    run,
    time,
    var,
    profile,
    rep,
    screenshot,
    animate,
    overwrite,
    window_size,
    max_frames,
    fps,
    progress,
    exaggeration=1.0,
) -> dict:
    exaggeration = _check_exaggeration(exaggeration)
    vals, scalar_title, cmap = field(run, var, rep, profile)
    times = np.asarray(run["time"].values)
    sun = np.asarray(run["sun_direction"].values) if ctio.has_variable(run, "sun_direction") else None
    i = select_time(times, time, sun)
    shot = ctio.check_output(screenshot, overwrite) if screenshot else None
    anim = ctio.check_output(animate, overwrite) if animate else None
    if anim is not None and anim.suffix.lower() not in (".gif", ".mp4"):
        raise ConfigError(f"animate={anim} must end in .gif or .mp4")
    if shot is None and anim is None and not _has_display():
        raise ConfigError(
            "no display for an interactive window; give a screenshot (--screenshot PNG) or an animation (--animate GIF)"
        )
    title = VARIABLES.get(var, ("", ""))[0] if profile is None else f"Profile {profile} minus nominal"
    out = dict(time=time_label(times[i]), screenshot=None, animation=None, n_frames=0)
    if not fps > 0:
        raise ConfigError(f"fps={fps} out of range (0, inf)")
    finite = vals[np.isfinite(vals)]
    if finite.size == 0:
        raise ConfigError(f"var={var!r} has no finite values to show")
    if profile is not None:
        m = float(np.abs(finite).max()) if finite.size else 1.0
        clim = (-max(m, 1e-3), max(m, 1e-3))
    else:
        clim = (float(finite.min()), float(max(finite.max(), finite.min() + 1e-3)))

    if shot is not None:
        # one time: colour range of that time (more contrast than the whole run's)
        v = vals[i]
        c = (float(v.min()), float(max(v.max(), v.min() + 1e-3))) if profile is None else clim
        snapshot(
            run,
            v,
            i,
            scalar_title,
            title,
            shot,
            cmap=cmap,
            clim=c,
            window_size=window_size,
            exaggeration=exaggeration,
            overwrite=overwrite,
        )
        out["screenshot"] = str(shot)
    if anim is not None:
        out["n_frames"] = _animate(
            run,
            vals,
            scalar_title,
            title,
            cmap,
            clim,
            anim,
            overwrite,
            window_size,
            _frame_indices(len(times), max_frames),
            fps,
            progress,
            exaggeration,
        )
        out["animation"] = str(anim)
    if shot is None and anim is None:  # pragma: no cover - needs a display
        scene = _Scene(run, scalar_title, cmap, clim, window_size, off_screen=False, exaggeration=exaggeration)
        scene.update(vals[i], i, title)
        scene.p.show()
    return out


def _animate(
    run,
    vals,
    scalar_title,
    title,
    cmap,
    clim,
    path: Path,
    overwrite: bool,
    window_size,
    frames,
    fps,
    progress,
    exaggeration: float = 1.0,
) -> int:
    from crater_thermal.progress import bar

    with ctio.atomic_output(path, overwrite) as tmp, bar("frames", progress) as report:
        scene = _Scene(run, scalar_title, cmap, clim, window_size, off_screen=True, exaggeration=exaggeration)
        try:
            _write_frames(scene, vals, title, tmp, frames, fps, report)
        finally:
            scene.close()  # also closes the MP4 writer, before the file is renamed into place
    return len(frames)


def _write_frames(scene, vals, title, tmp: Path, frames, fps, report) -> None:
    """Render ``frames`` into ``tmp``: an MP4 through imageio-ffmpeg, else a GIF through Pillow."""
    from PIL import Image

    movie = tmp.suffix.lower() == ".mp4"
    if movie:
        try:
            scene.p.open_movie(str(tmp), framerate=fps)
        except (ImportError, ValueError, RuntimeError):  # imageio or its ffmpeg plugin missing
            raise missing_extra("imageio-ffmpeg", "viz", "MP4 animations") from None
    images = []
    for n, i in enumerate(frames, 1):
        scene.update(vals[i], int(i), title)
        if movie:
            scene.p.write_frame()
        else:
            images.append(Image.fromarray(scene.image()).convert("P", palette=Image.ADAPTIVE))
        if report is not None:
            report(n, len(frames))
    if not movie:
        images[0].save(
            tmp, format="GIF", save_all=True, append_images=images[1:], duration=int(round(1000 / fps)), loop=0
        )
