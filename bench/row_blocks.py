"""Benchmark: the memory and product time of a distributed run's row blocks of the view-factor operator.

The generator crater of ``bench/scale.py`` (10 km crater, 5 km surround, 86 S) at ``--facets`` facets,
its operator (compressed from 20,000 facets, as a run builds it), saved as a distributed run saves it
(``vfoperator.save_operator``) and loaded back in the row blocks a run on ``--workers`` workers with
``--chunk-facets`` facets per chunk uses (``vfoperator.load_row_block``). Recorded: the whole operator's
bytes, each block's bytes (max, sum: the sum over the operator is the price of holding rows apart), the
time of one product with ``--samples`` right-hand sides (a window's emission) by the whole operator and
by every block, and the largest difference between the two (round-off). Products are timed after one
untimed call (compilation), ``--repeat`` times, alternating with the row blocks' product as it was made
before their float32 arithmetic (scipy's float64 CSR product of the near rows and the low-rank blocks in
float64: ``apply_float64_s``) and with the product as made before the far blocks were applied by halves
(every far block meeting the rows applied both ways: ``apply_whole_far_s``, whose result must equal the
shipped one bit for bit: ``equal_to_whole_far``); medians, so that the ratios come from one run.

Usage: ``python bench/row_blocks.py [--facets 30000] [--workers 2] [--chunk-facets 4000] [--samples 96]
[--repeat 3] [--out bench/results/row_blocks.json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from crater_thermal import geometry, raytrace, vfoperator  # noqa: E402


def apply_float64(blk, near64, X: np.ndarray) -> np.ndarray:
    """A compressed row block's product as it was made before the float32 arithmetic (float64 throughout,
    the near rows by scipy's CSR product of ``near64``, the block's near rows stored in float64 as they were
    then: converted once, outside the timing)."""
    from crater_thermal.kernels import vfoperator as kv

    Xc = np.ascontiguousarray(X[blk.perm])
    if blk.scale is not None:
        Xc *= blk.scale[:, None]
    Y = np.asarray(near64 @ Xc)
    full = np.zeros_like(Xc)
    kv.lowrank_matvec(*blk.lowrank, Xc, full, np.empty((2 * int(blk.lowrank[4].max()), Xc.shape[1])))
    Y += full[blk.a : blk.b]
    if blk.scale is not None:
        Y *= blk.scale[blk.a : blk.b, None]
    return Y / blk.areas[:, None]


def apply_whole_far(blk, X: np.ndarray) -> np.ndarray:
    """A compressed row block's product as it was made before its far blocks were applied by halves: every
    low-rank block meeting the rows applied both ways into an (n, k) array, the block's rows kept."""
    from crater_thermal.kernels import vfoperator as kv

    dtype = vfoperator.PRODUCT_DTYPE if X.shape[1] > 1 else np.float64
    Xc = np.ascontiguousarray(X[blk.perm], dtype)
    if blk.scale is not None:
        Xc *= blk.scale.astype(dtype)[:, None]
    Y = np.zeros((blk.b - blk.a, Xc.shape[1]), Xc.dtype)
    kv.csr_matmat(blk.near.indptr, blk.near.indices, blk.near.data, Xc, Y)
    if len(blk.lowrank[4]):
        full = np.zeros_like(Xc)
        kv.lowrank_matvec(*blk.lowrank, Xc, full, np.empty((2 * int(blk.lowrank[4].max()), Xc.shape[1]), Xc.dtype))
        Y += full[blk.a : blk.b]
    Y = Y.astype(np.float64, copy=False)
    if blk.scale is not None:
        Y *= blk.scale[blk.a : blk.b, None]
    return Y / blk.areas[:, None]


def _timed(f, *a) -> float:
    t0 = time.perf_counter()
    f(*a)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, default=30_000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk-facets", type=int, default=4000)
    ap.add_argument("--samples", type=int, default=96)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "row_blocks.json")
    args = ap.parse_args()
    mesh = geometry.crater_mesh(10.0, n_facets=args.facets, surround_km=5.0)
    t0 = time.perf_counter()
    F = vfoperator.view_factor_operator(mesh, raytrace.RayTracer(mesh))
    build_s = time.perf_counter() - t0
    nf = mesh.n_facets
    X = np.random.default_rng(0).uniform(20.0, 400.0, (nf, args.samples))  # emitted flux [W m-2]
    ref = F @ X
    whole_s = float(np.median([_timed(F.__matmul__, X) for _ in range(args.repeat)]))
    size = min(args.chunk_facets, -(-nf // args.workers))
    blocks = []
    with tempfile.TemporaryDirectory() as tmp:
        vfoperator.save_operator(F, tmp)
        for a in range(0, nf, size):
            b = min(nf, a + size)
            t0 = time.perf_counter()
            blk = vfoperator.load_row_block(tmp, a, b)
            load_s = time.perf_counter() - t0
            Y = blk.apply(X)
            near64 = blk.near.astype(np.float64)
            Y64 = apply_float64(blk, near64, X) if blk.perm is not None else Y
            Yw = apply_whole_far(blk, X) if blk.perm is not None else Y
            times = {"new": [], "old": [], "whole_far": []}
            for _ in range(args.repeat):
                times["old"].append(_timed(apply_float64, blk, near64, X) if blk.perm is not None else np.nan)
                times["whole_far"].append(_timed(apply_whole_far, blk, X) if blk.perm is not None else np.nan)
                times["new"].append(_timed(blk.apply, X))
            err = float(np.abs(Y - ref[blk.facets]).max())
            blocks.append(
                {
                    "rows": b - a,
                    "bytes": blk.nbytes,
                    "load_s": load_s,
                    "apply_s": float(np.median(times["new"])),
                    "apply_float64_s": float(np.median(times["old"])),
                    "apply_whole_far_s": float(np.median(times["whole_far"])),
                    "equal_to_whole_far": bool(np.array_equal(Y, Yw)),
                    "max_abs_diff": err,
                    "max_abs_diff_float64": float(np.abs(Y - Y64).max()),
                }
            )
    result = {
        "facets": nf,
        "operator": F.kind,
        "operator_bytes": int(F.nbytes),
        "operator_build_s": build_s,
        "samples": args.samples,
        "whole_product_s": whole_s,
        "chunk_facets": size,
        "blocks": blocks,
        "block_bytes_max": max(b["bytes"] for b in blocks),
        "block_bytes_sum_over_operator": sum(b["bytes"] for b in blocks) / F.nbytes,
        "block_products_s_sum_over_whole": sum(b["apply_s"] for b in blocks) / whole_s,
        "block_products_float64_over_shipped": sum(b["apply_float64_s"] for b in blocks)
        / sum(b["apply_s"] for b in blocks),
        "block_products_whole_far_over_shipped": sum(b["apply_whole_far_s"] for b in blocks)
        / sum(b["apply_s"] for b in blocks),
        "block_products_whole_far_s_sum_over_whole": sum(b["apply_whole_far_s"] for b in blocks) / whole_s,
        "product_dtype": np.dtype(vfoperator.PRODUCT_DTYPE).name,
        "largest_product_W_m2": float(np.abs(ref).max()),
        "max_abs_diff_W_m2": max(b["max_abs_diff"] for b in blocks),
        "max_abs_diff_float64_W_m2": max(b["max_abs_diff_float64"] for b in blocks),
        "loadavg": os.getloadavg(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "blocks"}))


if __name__ == "__main__":
    main()
