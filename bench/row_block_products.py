"""Benchmark: a distributed run's one-vector row-block product, one-vector kernels vs the several-vector ones.

A worker of a distributed run holds its chunk's rows of the compressed operator (``vfoperator.RowBlock``).
The periodic start's held first pass multiplies them by one vector per hold (366 holds a year). The
product goes through ``kernels.vfoperator.csr_matvec1`` and ``lowrank_matvec_rows1`` (one right-hand
side; a far block inside the rows applied both ways in one pass over its U factor); before, it went
through ``csr_matmat`` and ``lowrank_matvec_rows`` with one column. Both are timed here on the same
rows, alternating, on one numba thread (as a worker's task runs), in float64, and compared.

The generator crater of ``bench/scale.py`` (10 km, 5 km surround, 86 S) at ``--facets`` (default
30,000), its operator built, saved and read back as the rows ``0 .. facets/2`` (a 2-worker chunk).

Usage: ``python bench/row_block_products.py [--facets 30000] [--repeat 5] [--products 20] [--out FILE]``
(default ``bench/results/row_block_products.json``).
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scale import scale_mesh  # noqa: E402

from crater_thermal import cluster, vfoperator  # noqa: E402
from crater_thermal.kernels import vfoperator as kv  # noqa: E402


def several_vector_path(block, x: np.ndarray) -> np.ndarray:
    """The rows' product through the several-vector kernels with one column (the code before), float64."""
    Xc = np.ascontiguousarray(x[block.perm], np.float64)[:, None]
    if block.scale is not None:
        Xc *= block.scale[:, None]
    Y = np.zeros((block.b - block.a, 1))
    kv.csr_matmat(block.near.indptr, block.near.indices, block.near.data, Xc, Y)
    if len(block.lowrank[4]):
        far = np.zeros_like(Y)
        kv.lowrank_matvec_rows(
            *block.lowrank, Xc, far, np.empty((2 * int(block.lowrank[4].max()), 1)), block.a, block.b
        )
        Y += far
    if block.scale is not None:
        Y *= block.scale[block.a : block.b, None]
    return (Y / block.areas[:, None])[:, 0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, default=30_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--products", type=int, default=20, help="products per timing")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "row_block_products.json"))
    args = ap.parse_args()
    mesh = scale_mesh(args.facets)
    n = mesh.n_facets
    F = vfoperator.view_factor_operator(mesh, method="compressed")
    x = np.random.default_rng(0).random(n) * 400.0
    with tempfile.TemporaryDirectory() as tmp:
        vfoperator.save_operator(F, tmp)
        block = vfoperator.load_row_block(tmp, 0, n // 2)
    whole = (F @ x)[block.facets]
    one = block.apply(x[:, None])[:, 0]
    several = several_vector_path(block, x)
    times = {"one_vector_kernels_ms": [], "several_vector_kernels_ms": []}
    with cluster.one_numba_thread():
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            for _ in range(args.products):
                several_vector_path(block, x)
            t1 = time.perf_counter()
            for _ in range(args.products):
                block.apply(x[:, None])
            t2 = time.perf_counter()
            times["several_vector_kernels_ms"].append(round((t1 - t0) / args.products * 1e3, 3))
            times["one_vector_kernels_ms"].append(round((t2 - t1) / args.products * 1e3, 3))
    scale = float(np.abs(whole).max())
    out = {
        "benchmark": "row_block_products",
        "facets": n,
        "rows": int(len(block.facets)),
        "near_entries": int(block.near.nnz),
        "far_blocks": int(len(block.lowrank[4])),
        **times,
        "speedup_median": round(
            float(np.median(times["several_vector_kernels_ms"]) / np.median(times["one_vector_kernels_ms"])), 2
        ),
        "max_rel_diff_one_vs_whole": float(np.abs(one - whole).max() / scale),
        "max_rel_diff_several_vs_whole": float(np.abs(several - whole).max() / scale),
        "load_average": os.getloadavg(),
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
