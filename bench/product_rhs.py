"""Benchmark: what a product of the compressed operator costs by its number of right-hand sides (issue 24).

Run:  PYTHONPATH=$PWD python bench/product_rhs.py [--size 100000] [--rhs 1 8 16 24 25 32 48 49 64 96]
                                               [--repeat 3] [--out FILE]

The scale crater of ``bench/scale.py`` (10 km, 5 km flat surround, 86 S, ``--size`` facets) and its compressed
operator as a run builds it (a temporary cache), then, for each count k of ``--rhs``, an emission-like X
(eps sigma T^4, T drawn in 40-340 K; float32, in cluster order, as ``CompressedViewFactors`` hands it to its
kernels): the several-right-hand-side kernels on one thread, the low-rank part
(``kernels.vfoperator.lowrank_matvec``) and the near-field sparse part (``sym_sparse_matvec``), and the
whole product ``F @ X`` as a run makes it (both threads, the permutations and conversions included); the
best of ``--repeat`` each, and per right-hand side. The counts run in a shuffled order, the same for
each repeat round, so that this shared machine's load does not fall on the large ones only. Writes
``bench/results/product_rhs_<size>.json`` (or ``--out``); the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=100_000)
    ap.add_argument("--rhs", type=int, nargs="+", default=[1, 8, 16, 24, 25, 32, 48, 49, 64, 96])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="product_rhs_") as tmp:
        os.environ["CRATER_THERMAL_CACHE"] = tmp
        from scale import scale_mesh

        from crater_thermal import vfoperator
        from crater_thermal.constants import SIGMA
        from crater_thermal.kernels import vfoperator as kv

        mesh = scale_mesh(args.size)
        t0 = time.perf_counter()
        F = vfoperator.view_factor_operator(mesh, method="compressed")
        build_s = time.perf_counter() - t0
    n = F.shape[0]
    rng = np.random.default_rng(0)
    lowrank = (F.r0, F.r1, F.c0, F.c1, F.rank, F.uoff, F.voff, F.woff, F.U, F.V, F.W)
    rows = len(F.indptr) - 1
    order = list(rng.permutation(args.rhs))
    best: dict = {k: {"lowrank_1thread_s": np.inf, "sparse_1thread_s": np.inf, "product_s": np.inf} for k in args.rhs}
    data = {}
    for k in args.rhs:
        E = 0.95 * SIGMA * rng.uniform(40.0, 340.0, (n, k)) ** 4
        X = np.ascontiguousarray(E[F.perm], np.float32)
        data[k] = (E, X, np.empty((2 * F._max_rank, k), np.float32))
        # compiled for this layout, untimed
        kv.lowrank_matvec(*lowrank, X, np.zeros_like(X), data[k][2])
        kv.sym_sparse_matvec(F.indptr, F.indices, F.data, X, np.zeros_like(X), 0, rows)
        F @ E
    for _ in range(args.repeat):
        for k in order:
            E, X, tmp = data[k]
            Y = np.zeros_like(X)
            t = time.perf_counter()
            kv.lowrank_matvec(*lowrank, X, Y, tmp)
            best[k]["lowrank_1thread_s"] = min(best[k]["lowrank_1thread_s"], time.perf_counter() - t)
            Y = np.zeros_like(X)
            t = time.perf_counter()
            kv.sym_sparse_matvec(F.indptr, F.indices, F.data, X, Y, 0, rows)
            best[k]["sparse_1thread_s"] = min(best[k]["sparse_1thread_s"], time.perf_counter() - t)
            t = time.perf_counter()
            F @ E
            best[k]["product_s"] = min(best[k]["product_s"], time.perf_counter() - t)
    for k in args.rhs:
        best[k].update({f"{name[:-2]}_per_rhs_ms": 1e3 * v / k for name, v in list(best[k].items())})
    out = {
        "benchmark": "product_rhs",
        "facets": n,
        "operator_mb": F.nbytes / 1e6,
        "lowrank_numbers": int(((F.r1 - F.r0 + F.c1 - F.c0) * F.rank.astype(np.int64)).sum()),
        "sparse_entries": int(F.indptr[-1]),
        "build_s": build_s,
        "order": [int(k) for k in order],
        "by_rhs": {str(k): v for k, v in best.items()},
        "loadavg": list(os.getloadavg()),
        "cpus": os.cpu_count(),
    }
    path = args.out or HERE / "results" / f"product_rhs_{args.size}.json"
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
