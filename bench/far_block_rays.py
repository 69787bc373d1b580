"""Measurement: where the compressed operator's build spends its rays, and whether sampled rays could find
the far blocks in which nothing is visible (issue 24: the build's rays grow as N^2).

Run:  PYTHONPATH=$PWD python bench/far_block_rays.py [--sizes 5000 20000 100000] [--samples 4 8 16 32 64]

For each size, the terrain of ``bench/viewfactor_operator.py`` is built into the compressed operator
(tolerance 1e-3, one thread) with ``vfoperator._Builder.far_block`` wrapped by an instrumented copy that
traces every candidate pair of each far block as the build did before the occlusion proof
(``vfoperator.OCCLUSION_PROOF``; this script measures what that proof could save), then compresses the block with the
build's own ``_compress``. Per far block it records:

* the outcome: the whole block stored as one low-rank term (``lowrank_whole``), split with some low-rank
  children (``split_some_lowrank``), stored as sparse entries only (``sparse_only``), or nothing visible
  (``empty``: every candidate pair blocked, or no candidate); the rays and the wall seconds of the block
  (ray generation, tracing and compression) per outcome;
* a what-if screen: ``k`` candidate pairs drawn at random (``--samples``, seeded), and the block declared
  empty when none of them is visible. Blocks so declared that do have visible pairs are "missed"; the
  F row sums they would lose (F = G / A_i, i.e. the error of F·1) are mapped to facets and compared with
  the operator's row sums. Nothing of the build is changed: the operator built is the normal one.

Writes ``bench/results/far_block_rays.json`` (``--out``); the last stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

OUTCOMES = ("lowrank_whole", "split_some_lowrank", "sparse_only", "empty")


def measure(n_facets: int, samples: tuple[int, ...], seed: int = 1) -> dict:
    """Build one operator with the instrumented far blocks; return the split and the screen's what-if."""
    from viewfactor_operator import terrain

    from crater_thermal import vfoperator as vo
    from crater_thermal.kernels import vfoperator as kv
    from crater_thermal.raytrace import RayTracer

    mesh = terrain(n_facets)
    tracer = RayTracer(mesh)
    rng = np.random.default_rng(seed)
    by = {k: {"blocks": 0, "rays": 0, "s": 0.0} for k in OUTCOMES}
    screen = {k: {"flagged": 0, "flagged_rays": 0, "missed": 0, "missed_fro2": 0.0} for k in samples}
    fro2_all = [0.0]
    lost: dict[int, np.ndarray] = {}

    def far_block(self, s, t):
        t0 = time.perf_counter()
        tree = self.tree
        r0, r1, c0, c1 = int(tree.lo[s]), int(tree.hi[s]), int(tree.lo[t]), int(tree.hi[t])
        m, n = r1 - r0, c1 - c0
        o32 = np.empty((m * n, 3), np.float32)
        d32 = np.empty((m * n, 3), np.float32)
        pos = np.empty(m * n, np.int64)
        val = np.empty(m * n)
        k = kv.far_block_rays(r0, r1, c0, c1, self.C, self.N, self.P, self.A, self.cos_cut, o32, d32, pos, val)
        M = np.zeros(m * n)
        visible = np.zeros(0, bool)
        if k:
            blocked = self._trace(o32, d32, k)
            kv.scatter_visible(k, pos, val, blocked, M)
            visible = blocked[:k] == -1
        M = M.reshape(m, n)
        fro2 = float(np.einsum("ij,ij->", M, M))
        fro2_all[0] += fro2
        for K in samples:
            lost.setdefault(K, np.zeros(len(self.A)))
            if k == 0:
                continue
            draw = rng.choice(k, size=min(K, k), replace=False)
            if not visible[draw].any():
                sc = screen[K]
                sc["flagged"] += 1
                sc["flagged_rays"] += k - len(draw)
                if visible.any():
                    sc["missed"] += 1
                    sc["missed_fro2"] += fro2
                    lost[K][r0:r1] += M.sum(axis=1)
        lowrank, coo = [], []
        self._compress(M, s, t, lowrank, coo)
        if not lowrank and not coo:
            kind = "empty"
        elif coo or len(lowrank) > 1 or lowrank[0][2].shape[0] != m or lowrank[0][3].shape[0] != n:
            kind = "split_some_lowrank" if lowrank else "sparse_only"
        else:
            kind = "lowrank_whole"
        b = by[kind]
        b["blocks"] += 1
        b["rays"] += k
        b["s"] += time.perf_counter() - t0
        return lowrank, coo, k, 0

    original = vo._Builder.far_block
    vo._Builder.far_block = far_block
    try:
        t0 = time.perf_counter()
        F = vo.compressed_view_factors(mesh, tracer, n_threads=1)
        build_s = time.perf_counter() - t0
    finally:
        vo._Builder.far_block = original
    rays = sum(b["rays"] for b in by.values())
    secs = sum(b["s"] for b in by.values())
    rowsum = F.row_sums()
    out = {
        "facets": int(len(rowsum)),
        "build_s": build_s,
        "rays": int(F.stats["rays"]),
        "far_rays": int(rays),
        "far_blocks_s": secs,
        "outcomes": {k: {**b, "ray_share": b["rays"] / rays, "time_share": b["s"] / secs} for k, b in by.items()},
        "screen": {},
    }
    for K in samples:
        sc = screen[K]
        err = np.zeros(len(rowsum))
        err[F.perm] = lost[K] / F.areas_perm  # F row sums lost, facet order [-]
        out["screen"][str(K)] = {
            "declared_empty_blocks": sc["flagged"],
            "rays_saved_share": sc["flagged_rays"] / rays,
            "missed_blocks": sc["missed"],
            "missed_fro2_share": sc["missed_fro2"] / fro2_all[0],
            "rowsum_error_max_over_max_rowsum": float(err.max() / rowsum.max()),
            "rowsum_error_max_relative": float(np.max(err / np.maximum(rowsum, 1e-300))),
            "rowsum_error_rel_l2": float(np.linalg.norm(err) / np.linalg.norm(rowsum)),
        }
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000, 100000])
    ap.add_argument("--samples", type=int, nargs="+", default=[4, 8, 16, 32, 64])
    ap.add_argument("--out", default=str(HERE / "results" / "far_block_rays.json"))
    args = ap.parse_args(argv)
    res = {"tolerance": 1e-3, "threads": 1, "sizes": []}
    for n in args.sizes:
        r = measure(n, tuple(args.samples))
        print(json.dumps(r), flush=True)
        res["sizes"].append(r)
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
