"""Benchmark: compressed view-factor operator against the exact sparse matrix (issue 13, item 2).

Run:  PYTHONPATH=$PWD python bench/viewfactor_operator.py [--sizes 10000 25000 50000] [--big 100000]
      [--row-tolerance 0.003 0.01 0.03]  (also the row-relative operator, issue 24: each tolerance is a
      variant ``compressed-row@TOL`` built, timed and compared like the default one)
      [--old-tree DIR --pairs P]  (the --big sizes built by another source tree's code and this one's,
      alternating, old first: ``pairs`` in the JSON, with build time and peak ratios and whether the
      products are bit for bit equal)

Terrain: a synthetic crater-in-terrain height field (20 km square, a 10 km paraboloid crater 2 km deep
with a raised rim, 20 m Gaussian roughness), two triangles per grid cell, at each size.  Every
(size, method) is built in its own subprocess, so that ``peak_rss_mb`` (``ru_maxrss``) is that build's
own peak (mesh, tracer and numba included; ``rss_before_mb`` is the same process before the build).
Each subprocess also times products ``F @ x`` (median of 5; with 16 and 64 right-hand sides, median of 3
after one) and saves them for three fields:

* ``emitted``: ``eps sigma T^4`` of a day-time temperature field (radiative equilibrium with the direct
  sunlight of a Sun 10 deg high, shadowed facets at 50 K),
* ``scattered``: the first-bounce exitance ``albedo E`` of the same sunlight,
* ``ones``: row sums.

The parent compares them (relative 2-norm error, largest row-sum difference) and fits growth exponents
``log(q2 / q1) / log(N2 / N1)`` between the two largest sizes of each method (``--big`` included for the
compressed operator).  Times are wall-clock and CPU (both threads) seconds; the machine may be shared,
so ``load_average`` is recorded.  The last stdout line is one JSON object, also written to
``bench/results/viewfactor_operator.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def terrain(n_facets: int, seed: int = 0):
    from crater_thermal.geometry import Mesh

    k = max(2, int(round(np.sqrt(n_facets / 2.0))))
    x = np.linspace(-10_000.0, 10_000.0, k + 1)
    X, Y = np.meshgrid(x, x)
    r = np.hypot(X, Y)
    R, depth = 5_000.0, 2_000.0
    z = np.where(r < R, -depth * (1 - (r / R) ** 2), 0.0)
    z += np.where(r >= R, 0.08 * depth * np.exp(-(((r - R) / (0.3 * R)) ** 2)), 0.08 * depth * (r / R) ** 2)
    z += 20.0 * np.random.default_rng(seed).standard_normal(z.shape)
    V = np.column_stack([X.ravel(), Y.ravel(), z.ravel()])
    idx = np.arange((k + 1) ** 2).reshape(k + 1, k + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return Mesh(V, np.concatenate([np.stack([a, b, d], 1), np.stack([b, c, d], 1)]), {"kind": "file"})


#: Compressed variants: bench name -> ``tolerance_mode`` of :func:`compressed_view_factors`.
MODES = {"compressed": "block", "compressed-row": "row"}


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child(method: str, n: int, tol: float, out_npz: str) -> dict:
    """One build in this process: times, memory, products saved to ``out_npz``."""
    from crater_thermal import illumination
    from crater_thermal import vfoperator as vo
    from crater_thermal import viewfactors as vf
    from crater_thermal.constants import AU, SIGMA
    from crater_thermal.raytrace import RayTracer

    small = terrain(600)
    kind = "exact" if method == "exact" else "compressed"
    mode = MODES.get(method, "block")
    warm = vo.view_factor_operator(small, RayTracer(small), method=kind, tolerance=tol, tolerance_mode=mode)  # warm-up
    warm @ np.ones(small.n_facets), warm @ np.ones((small.n_facets, 2))
    mesh = terrain(n)
    tracer = RayTracer(mesh)
    sun = illumination.sun_direction_from_angles(10.0, 200.0)
    E = illumination.direct_irradiance(mesh, tracer, sun[None], np.array([AU]))[0]
    T = np.maximum((0.88 * E / (0.95 * SIGMA)) ** 0.25, 50.0)
    fields = {"emitted": 0.95 * SIGMA * T**4, "scattered": 0.12 * E, "ones": np.ones(mesh.n_facets)}
    rss0 = _rss_mb()
    w0, c0 = time.perf_counter(), time.process_time()
    if method == "exact":
        op = vo.SparseViewFactors(vf.view_factor_matrix(mesh, tracer))
    else:
        op = vo.compressed_view_factors(mesh, tracer, tol, tolerance_mode=MODES[method])
    build_s, build_cpu_s = time.perf_counter() - w0, time.process_time() - c0
    peak = _rss_mb()
    prods = {k: op @ x for k, x in fields.items()}
    times = []
    for _ in range(5):
        t = time.perf_counter()
        op @ fields["emitted"]
        times.append(time.perf_counter() - t)
    # several right-hand sides (a lagged window's 16, scattering's 64), after one product that compiles
    # the kernels for this operator's arrays: the median of 3
    matmat = {}
    for k in (16, 64):
        X = np.column_stack([fields["emitted"]] * k)
        op @ X
        ts = []
        for _ in range(3):
            t = time.perf_counter()
            op @ X
            ts.append(time.perf_counter() - t)
        matmat[k] = float(np.median(ts))
    np.savez(out_npz, **prods)
    res = {
        "method": method,
        "tolerance": tol,
        "facets": mesh.n_facets,
        "build_s": build_s,
        "build_cpu_s": build_cpu_s,
        "nbytes": int(op.nbytes),
        "rss_before_mb": rss0,
        "peak_rss_mb": peak,
        "matvec_s": float(np.median(times)),
        "matmat16_s": matmat[16],
        "matmat64_s": matmat[64],
    }
    if method == "exact":
        res["nnz"] = int(op.nnz)
    else:
        res["stats"] = op.stats
    return res


def _run_child(method, n, tol, tmp, tree=None, tag="") -> tuple[dict, str]:
    """One build in its own process; ``tree``: another source tree (its own copy of this script and its
    package on ``PYTHONPATH``, this virtual environment), for ``--old-tree``."""
    npz = os.path.join(tmp, f"{method}_{tol:g}_{n}{tag}.npz")
    script = __file__ if tree is None else str(Path(tree) / "bench" / "viewfactor_operator.py")
    cmd = [sys.executable, script, "--child", method, str(n), "--tolerance", str(tol), "--npz", npz]
    env = os.environ.copy() if tree is None else dict(os.environ, PYTHONPATH=str(tree))
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if p.returncode != 0:
        return {"method": method, "facets": n, "error": p.stderr.strip().splitlines()[-1:]}, npz
    res = json.loads(p.stdout.strip().splitlines()[-1])
    print(json.dumps(res), file=sys.stderr, flush=True)
    return res, npz


def _exponent(rows, key):
    rows = [r for r in rows if key in r]
    if len(rows) < 2:
        return None
    a, b = rows[-2], rows[-1]
    return float(np.log(b[key] / a[key]) / np.log(b["facets"] / a["facets"]))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 25_000, 50_000])
    ap.add_argument("--big", type=int, nargs="*", default=[100_000], help="compressed operator only")
    ap.add_argument("--exact-max", type=int, default=50_000, help="largest size built exactly")
    ap.add_argument("--tolerance", type=float, default=None)
    ap.add_argument(
        "--row-tolerance",
        type=float,
        nargs="*",
        default=[],
        help="also build the row-relative operator (tolerance_mode='row') at these tolerances",
    )
    ap.add_argument(
        "--old-tree",
        default=None,
        help="also build the default compressed operator of --big with the code of this source tree, "
        "alternating with this one (old first), --pairs times: paired build time and peak memory",
    )
    ap.add_argument("--pairs", type=int, default=1)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "viewfactor_operator.json"))
    ap.add_argument("--child", nargs=2, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--npz", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    from crater_thermal import vfoperator as vo

    tol = vo.DEFAULT_TOLERANCE if args.tolerance is None else args.tolerance
    if args.child:
        res = child(args.child[0], int(args.child[1]), tol, args.npz)
        print(json.dumps(res))
        return res

    load0 = os.getloadavg()
    variants = [("compressed", tol)] + [("compressed-row", float(t)) for t in args.row_tolerance]
    rows_exact, errors = [], []
    rows_comp = {f"{m}@{t:g}": [] for m, t in variants}
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            ex = None
            if n <= args.exact_max:
                ex, npz_e = _run_child("exact", n, tol, tmp)
                rows_exact.append(ex)
            for m, t in variants:
                co, npz_c = _run_child(m, n, t, tmp)
                rows_comp[f"{m}@{t:g}"].append(co)
                if ex is not None and "error" not in ex and "error" not in co:
                    with np.load(npz_e) as ze, np.load(npz_c) as zc:
                        err = {"variant": f"{m}@{t:g}", "facets": co["facets"]}
                        for k in ("emitted", "scattered"):
                            err[f"rel_error_{k}"] = float(np.linalg.norm(zc[k] - ze[k]) / np.linalg.norm(ze[k]))
                            err[f"max_abs_error_over_max_{k}"] = float(
                                np.max(np.abs(zc[k] - ze[k]) / np.abs(ze[k]).max())
                            )
                        err["rowsum_max_abs_diff"] = float(np.abs(zc["ones"] - ze["ones"]).max())
                        err["rowsum_max_exact"] = float(ze["ones"].max())
                        err["memory_ratio"] = ex["nbytes"] / co["nbytes"]
                        errors.append(err)
                        print(json.dumps(err), file=sys.stderr, flush=True)
        pairs = []
        for n in args.big:
            if args.old_tree:
                for q in range(args.pairs):
                    old, npz_o = _run_child("compressed", n, tol, tmp, args.old_tree, "_old")
                    new, npz_n = _run_child("compressed", n, tol, tmp, None, "_new")
                    pair = {"facets": n, "pair": q, "old": old, "new": new}
                    if "error" not in old and "error" not in new:
                        with np.load(npz_o) as zo, np.load(npz_n) as zn:
                            pair["products_equal"] = all(np.array_equal(zo[k], zn[k]) for k in zo.files)
                            pair["products_max_rel_diff"] = {
                                k: float(np.abs(zn[k] - zo[k]).max() / np.abs(zo[k]).max()) for k in zo.files
                            }
                        for k in (
                            "build_s",
                            "build_cpu_s",
                            "peak_rss_mb",
                            "nbytes",
                            "matvec_s",
                            "matmat16_s",
                            "matmat64_s",
                        ):
                            if k in old and k in new:
                                pair[f"{k}_old_over_new"] = old[k] / new[k]
                        pair["peak_over_stored_old"] = old["peak_rss_mb"] * 2**20 / old["nbytes"]
                        pair["peak_over_stored_new"] = new["peak_rss_mb"] * 2**20 / new["nbytes"]
                    pairs.append(pair)
                    print(json.dumps({k: v for k, v in pair.items() if k not in ("old", "new")}), file=sys.stderr)
                continue
            for m, t in variants:
                co, _ = _run_child(m, n, t, tmp)
                rows_comp[f"{m}@{t:g}"].append(co)
    ok_e = [r for r in rows_exact if "error" not in r]
    keys = ("build_s", "build_cpu_s", "nbytes", "peak_rss_mb", "matvec_s")
    exps = {"exact": {k: _exponent(ok_e, k) for k in keys}}
    for v, rows in rows_comp.items():
        exps[v] = {k: _exponent([r for r in rows if "error" not in r], k) for k in keys}
    result = {
        "tolerance": tol,
        "terrain": "20 km height field, 10 km paraboloid crater 2 km deep, raised rim, 20 m roughness",
        "exact": rows_exact,
        "compressed": rows_comp.pop(f"compressed@{tol:g}"),
        **({"compressed_variants": rows_comp} if rows_comp else {}),
        "errors": errors,
        "exponents": exps,
        **({"old_tree": str(args.old_tree), "pairs": pairs} if args.old_tree else {}),
        "load_average_start": load0,
        "load_average_end": os.getloadavg(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
