"""Benchmark: the memory and product time of a distributed run's row blocks of the view-factor operator.

The generator crater of ``bench/scale.py`` (10 km crater, 5 km surround, 86 S) at ``--facets`` facets,
its operator (compressed from 20,000 facets, as a run builds it), saved as a distributed run saves it
(``vfoperator.save_operator``) and loaded back in the row blocks a run on ``--workers`` workers with
``--chunk-facets`` facets per chunk uses (``vfoperator.load_row_block``). Recorded: the whole operator's
bytes, each block's bytes (max, sum: the sum over the operator is the price of holding rows apart), the
time of one product with ``--samples`` right-hand sides (a window's emission) by the whole operator and
by every block, and the largest difference between the two (round-off).

Usage: ``python bench/row_blocks.py [--facets 30000] [--workers 2] [--chunk-facets 4000] [--samples 96]
[--out bench/results/row_blocks.json]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from crater_thermal import geometry, raytrace, vfoperator  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, default=30_000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--chunk-facets", type=int, default=4000)
    ap.add_argument("--samples", type=int, default=96)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "row_blocks.json")
    args = ap.parse_args()
    mesh = geometry.crater_mesh(10.0, n_facets=args.facets, surround_km=5.0)
    t0 = time.perf_counter()
    F = vfoperator.view_factor_operator(mesh, raytrace.RayTracer(mesh))
    build_s = time.perf_counter() - t0
    nf = mesh.n_facets
    X = np.random.default_rng(0).uniform(20.0, 400.0, (nf, args.samples))  # emitted flux [W m-2]
    t0 = time.perf_counter()
    ref = F @ X
    whole_s = time.perf_counter() - t0
    size = min(args.chunk_facets, -(-nf // args.workers))
    blocks = []
    with tempfile.TemporaryDirectory() as tmp:
        vfoperator.save_operator(F, tmp)
        for a in range(0, nf, size):
            b = min(nf, a + size)
            t0 = time.perf_counter()
            blk = vfoperator.load_row_block(tmp, a, b)
            load_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            Y = blk.apply(X)
            apply_s = time.perf_counter() - t0
            err = float(np.abs(Y - ref[blk.facets]).max())
            blocks.append(
                {"rows": b - a, "bytes": blk.nbytes, "load_s": load_s, "apply_s": apply_s, "max_abs_diff": err}
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
        "max_abs_diff_W_m2": max(b["max_abs_diff"] for b in blocks),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "blocks"}))


if __name__ == "__main__":
    main()
