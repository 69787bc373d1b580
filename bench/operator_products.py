"""Benchmark: products of the compressed view-factor operator in float32 against float64 arithmetic (issue 24).

Run:  PYTHONPATH=$PWD python bench/operator_products.py [--size 30000] [--repeat 4]

Builds the scale crater of ``bench/scale.py`` (10 km, 5 km flat surround, 86 S, ``--size`` facets, cold cache)
and its compressed operator, then times products ``F X`` of an emission-like X (eps sigma T^4 of T drawn in
40-340 K) with 8 and 64 right-hand sides (the lagged windows' and scattering's way; one right-hand side, the
coupled step's, is always float64: float32 was no faster there, 0.95x, ``operator_products_30000_one_rhs.json``,
measured before that choice),
float64 and float32 arithmetic (``CompressedViewFactors.product_dtype``) alternating in this one process,
``--repeat`` times each; and with one right-hand side (float64), the kernels as shipped (reassociated sums,
``kernels.vfoperator.ONE_RHS_FASTMATH``) against their source compiled without those flags, alternating,
5 x ``--repeat`` times each (``one_rhs_fastmath`` in the JSON). Accuracy of float32 against float64 on the
same X: per facet relative difference (facets above 1e-6 of the column's largest), its largest and median.
``as_shipped``: products of 1, 2, 4 and 8 right-hand sides made as a run makes them, alternating, 3 x
``--repeat`` times each: the cost of k right-hand sides against one. Writes
``bench/results/operator_products_<size>.json``; the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def one_rhs_fastmath(F, x, repeat: int) -> dict:
    """One right-hand side (the coupled step's product, float64): the kernels as shipped (LLVM flags
    ``kernels.vfoperator.ONE_RHS_FASTMATH``) against the same Python source compiled without them, alternating
    in this process; the largest relative difference of the products (facets above 1e-6 of the largest)."""
    from numba import njit

    from crater_thermal.kernels import vfoperator as kv

    names = ("sym_sparse_matvec1", "lowrank_matvec1")
    shipped = {name: getattr(kv, name) for name in names}
    plain = {name: njit(nogil=True)(shipped[name].py_func) for name in names}
    out, times = {}, {"plain": [], "fastmath": []}
    try:
        for label, kernels in (("plain", plain), ("fastmath", shipped)):  # warm-up: compilation, the pool
            for name in names:
                setattr(kv, name, kernels[name])
            out[label] = F @ x
        for _ in range(repeat):
            for label, kernels in (("plain", plain), ("fastmath", shipped)):
                for name in names:
                    setattr(kv, name, kernels[name])
                t0 = time.perf_counter()
                F @ x
                times[label].append(time.perf_counter() - t0)
    finally:
        for name in names:
            setattr(kv, name, shipped[name])
    ref = out["plain"]
    lit = ref > 1e-6 * ref.max()
    med = {n: float(np.median(t)) for n, t in times.items()}
    return {
        "right_hand_sides": 1,
        "flags": sorted(kv.ONE_RHS_FASTMATH),
        "seconds": times,
        "median_s": med,
        "plain_over_fastmath": med["plain"] / med["fastmath"],
        "max_rel_diff": float((np.abs(out["fastmath"] - ref)[lit] / ref[lit]).max()),
    }


def as_shipped(F, X, repeat: int, counts=(1, 2, 4, 8)) -> dict:
    """Products with 1, 2, 4 and 8 right-hand sides as a run makes them (one in float64, several in
    :data:`crater_thermal.vfoperator.PRODUCT_DTYPE`), the counts alternating in this process: what a
    product of k right-hand sides costs against k products of one (a coupled step's products made two at
    a time, for example). Median seconds per product and per right-hand side."""
    times = {str(k): [] for k in counts}
    for k in counts:  # warm-up
        F @ (X[:, 0] if k == 1 else X[:, :k])
    for _ in range(repeat):
        for k in counts:
            x = X[:, 0] if k == 1 else X[:, :k]
            t0 = time.perf_counter()
            F @ x
            times[str(k)].append(time.perf_counter() - t0)
    med = {k: float(np.median(t)) for k, t in times.items()}
    return {
        "seconds": times,
        "median_s": med,
        "per_rhs_s": {k: med[k] / int(k) for k in med},
        "over_one": {k: med[k] / med["1"] for k in med},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=30_000)
    ap.add_argument("--repeat", type=int, default=4)
    args = ap.parse_args()
    spec = importlib.util.spec_from_file_location("scale", HERE / "scale.py")
    scale = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(scale)
    from crater_thermal import config, simulate, vfoperator

    with tempfile.TemporaryDirectory(prefix="products_") as tmp:
        os.environ["CRATER_THERMAL_CACHE"] = str(Path(tmp) / "cache")
        path = Path(tmp) / "case.toml"
        path.write_text(scale.case_text(args.size, "2019-01-03T00:00"))
        case = config.load_case(path)
        mesh, _, F = simulate.case_geometry(case, simulate.Timer())
    if not isinstance(F, vfoperator.CompressedViewFactors):
        raise SystemExit(f"{args.size} facets gave a {type(F).__name__}; use >= 10,000 facets (compressed operator)")
    rng = np.random.default_rng(1)
    X = 0.95 * 5.670374419e-8 * (40.0 + 300.0 * rng.random((mesh.n_facets, 64))) ** 4
    result = {"benchmark": "operator_products", "facets": mesh.n_facets, "operator_mb": F.nbytes / 1e6, "cases": {}}
    for k in (8, 64):
        x = X[:, :k]
        out, times = {}, {"float64": [], "float32": []}
        for dtype in (np.float64, np.float32):  # warm-up: numba compilation or cache load, the thread pool
            F.product_dtype = dtype
            out[dtype] = F @ x
        for _ in range(args.repeat):
            for name, dtype in (("float64", np.float64), ("float32", np.float32)):
                F.product_dtype = dtype
                t0 = time.perf_counter()
                F @ x
                times[name].append(time.perf_counter() - t0)
        ref = out[np.float64].reshape(mesh.n_facets, -1)
        got = out[np.float32].reshape(ref.shape)
        lit = ref > 1e-6 * ref.max(axis=0)
        rel = np.abs(got - ref)[lit] / ref[lit]
        med = {n: float(np.median(t)) for n, t in times.items()}
        result["cases"][str(k)] = {
            "right_hand_sides": k,
            "seconds": times,
            "median_s": med,
            "float64_over_float32": med["float64"] / med["float32"],
            "max_rel_diff": float(rel.max()),
            "median_rel_diff": float(np.median(rel)),
        }
        print(json.dumps({"k": k, **{a: b for a, b in result["cases"][str(k)].items() if a != "seconds"}}), flush=True)
    F.product_dtype = vfoperator.PRODUCT_DTYPE
    result["as_shipped"] = as_shipped(F, X, args.repeat * 3)
    print(json.dumps({"as_shipped": result["as_shipped"]["median_s"]}), flush=True)
    result["one_rhs_fastmath"] = one_rhs_fastmath(F, X[:, 0], args.repeat * 5)
    print(json.dumps({"k": 1, **{a: b for a, b in result["one_rhs_fastmath"].items() if a != "seconds"}}), flush=True)
    result["loadavg"] = os.getloadavg()
    (HERE / "results" / f"operator_products_{args.size}.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
