"""Benchmark: ``crater-thermal steady`` on large plain-with-bowl height fields (issue 20, item 5).

Run:  PYTHONPATH=$PWD .venv/bin/python bench/steady.py [--sizes 30752 100352] [--sun-elevation-deg 10]
                                                       [--view-factors auto] [--solver auto]
                                                       [--terrain plain_bowl | crater_terrain]

Terrain (the issue's case): a flat plain 20 km square with a spherical bowl crater 10 km across,
depth/diameter 0.2, in its middle (``crater_thermal.reference.spherical_bowl``), meshed as a height field of
k x k cells, two triangles each (``crater_thermal.reference.grid_mesh``): 30,752 facets is k = 124, 100,352 is
k = 224. Issue 20 reports that ``steady`` used to end on such a 30,752-facet terrain in ``internal
error: MemoryError`` after ~70 s (the sparse LU of I - A F). The Sun is 10 deg high in the south
(azimuth 180 deg), the default limb-darkened disk; albedo 0.12, emissivity 0.95.

``--terrain crater_terrain``: the harder terrain of ``bench/viewfactor_operator.py`` instead (a paraboloid
crater with a raised rim and 20 m Gaussian roughness everywhere, so that the plain's facets see each other
too: at 100k facets its compressed operator takes 329 MB against the plain-with-bowl's 89 MB), for
comparison with that benchmark's 100k operator build (peak RSS 1.27 GB).

Each size runs the real command (``python -m crater_thermal steady MESH ... -o OUT``) in its own
subprocess, from process start to the written file: wall time, CPU time (user + system, both cores) and
peak resident set (``ru_maxrss`` of that child, from ``os.wait4``). The parent builds and saves the mesh
before it starts the child (not timed), and reads back from the written file the methods it says it
used (attributes ``view_factors``, ``solver``, ``scattering_solve``, ``ir_solve``, ``view_factor_bytes``)
and the temperature range. The machine is shared: ``loadavg`` holds ``os.getloadavg()`` before and
after each size. The last stdout line is one JSON object, also written to ``bench/results/steady.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from crater_thermal.reference import grid_mesh, spherical_bowl  # noqa: E402

#: Terrain [m]: side of the square plain, diameter of the bowl; the bowl's depth/diameter [-].
SIZE_M, DIAMETER_M, DEPTH_TO_DIAMETER = 20_000.0, 10_000.0, 0.2
#: What ``run`` reached at 100k facets (docs/performance.md, Scale): peak resident set [MB] of a whole year's run.
RUN_PEAK_100K_MB = 1853


def plain_with_bowl(n_facets: int):
    """The benchmark terrain with about ``n_facets`` facets (2 k^2, k = round(sqrt(n / 2)))."""
    k = max(2, int(round(math.sqrt(n_facets / 2.0))))
    x = np.linspace(-SIZE_M / 2, SIZE_M / 2, k + 1)
    X, Y = np.meshgrid(x, x)
    return grid_mesh(x, x, spherical_bowl(np.hypot(X, Y), DIAMETER_M, DEPTH_TO_DIAMETER)), k


def crater_terrain(n_facets: int):
    """``bench/viewfactor_operator.terrain`` (rim, roughness) with about ``n_facets`` facets."""
    sys.path.insert(0, str(REPO / "bench"))
    from viewfactor_operator import terrain

    k = max(2, int(round(math.sqrt(n_facets / 2.0))))
    return terrain(n_facets), k


def run_one(n_facets: int, args, workdir: Path) -> dict:
    """Mesh, then the ``steady`` command in a child process; its time, memory and what it wrote."""
    from crater_thermal.geometry import save_mesh

    mesh, k = plain_with_bowl(n_facets) if args.terrain == "plain_bowl" else crater_terrain(n_facets)
    mesh_path = workdir / f"plain_bowl_{mesh.n_facets}.ply"
    out = workdir / f"steady_{mesh.n_facets}.nc"
    save_mesh(mesh, mesh_path, overwrite=True)
    cmd = [
        sys.executable, "-m", "crater_thermal", "steady", str(mesh_path),
        "--sun-elevation-deg", str(args.sun_elevation_deg), "--sun-azimuth-deg", "180",
        "--albedo", "0.12", "--emissivity", "0.95",
        "--view-factors", args.view_factors, "--solver", args.solver,
        "-o", str(out), "--overwrite",
    ]  # fmt: skip
    env = dict(os.environ, CRATER_THERMAL_QUIET="1", PYTHONPATH=str(REPO))
    load0 = os.getloadavg()
    with open(workdir / "stdout.txt", "w+") as so, open(workdir / "stderr.txt", "w+") as se:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=so, stderr=se, env=env, cwd=REPO)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        so.seek(0)
        se.seek(0)
        stdout, stderr = so.read().strip(), se.read().strip()
    row = {
        "facets": mesh.n_facets,
        "grid_cells": f"{k} x {k}",
        "returncode": proc.returncode,
        "wall_s": round(wall, 1),
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
        "peak_rss_mb": round(usage.ru_maxrss / 1024.0, 1),  # Linux: ru_maxrss in KB
        "loadavg": [round(load0[0], 2), round(os.getloadavg()[0], 2)],
        "stdout": stdout.splitlines()[-1] if stdout else "",
        "stderr_tail": stderr.splitlines()[-3:] if stderr else [],
    }
    if proc.returncode == 0:
        import xarray as xr

        with xr.open_dataset(out) as ds:
            for key in ("view_factors", "view_factor_tolerance", "view_factor_bytes", "solver"):
                v = ds.attrs.get(key)
                row[key] = v.item() if hasattr(v, "item") else v
            row["scattering_solve"] = ds.attrs.get("scattering_solve")
            row["ir_solve"] = ds.attrs.get("ir_solve")
            T = ds["surface_temperature"].values
            row["surface_temperature_K"] = [round(float(T.min()), 2), round(float(T.max()), 2)]
        out.unlink()
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[30_752, 100_352])
    p.add_argument("--sun-elevation-deg", type=float, default=10.0)
    p.add_argument("--view-factors", default="auto")
    p.add_argument("--solver", default="auto")
    p.add_argument("--terrain", choices=("plain_bowl", "crater_terrain"), default="plain_bowl")
    p.add_argument("--output", type=Path, default=REPO / "bench" / "results" / "steady.json")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_steady_") as tmp:
        rows = [run_one(n, args, Path(tmp)) for n in args.sizes]
    result = {
        "benchmark": "bench/steady.py",
        "terrain": (
            f"plain {SIZE_M / 1000:g} km square with a spherical bowl {DIAMETER_M / 1000:g} km across, "
            f"depth/diameter {DEPTH_TO_DIAMETER:g}, height field (reference.grid_mesh), 2 triangles per cell"
            if args.terrain == "plain_bowl"
            else "bench/viewfactor_operator.terrain: 20 km square, 10 km paraboloid crater 2 km deep, raised rim, "
            "20 m Gaussian roughness, height field, 2 triangles per cell"
        ),
        "sun": f"elevation {args.sun_elevation_deg:g} deg, azimuth 180 deg, limb-darkened disk (default)",
        "requested": {"view_factors": args.view_factors, "solver": args.solver},
        "run_peak_rss_100k_mb": RUN_PEAK_100K_MB,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "sizes": rows,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
