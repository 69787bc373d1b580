"""Benchmark: the compressed operator's build with and without the terrain's occlusion proof (issue 24),
alternating in one process.

Run:  PYTHONPATH=$PWD python bench/occlusion_proof.py [--terrain rough scale] [--sizes 20000 100000]
                                                     [--order off on on off]

``rough``: the crater-in-terrain height field of ``bench/viewfactor_operator.py`` (20 m roughness);
``scale``: the generator's 10 km crater with its 5 km flat surround of ``bench/scale.py`` (the mesh of a
scale run). For each terrain and size, the operator is built (tolerance 1e-3, the tracer's threads) with
``vfoperator.OCCLUSION_PROOF`` off and on in the order ``--order``; each build's wall seconds and rays are
recorded, and the arrays of the two operators are compared (the proof only skips rays that would be
blocked, so they must be equal). Writes ``bench/results/occlusion_proof.json`` (``--out``); the last
stdout line is the same JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def mesh_of(terrain_name: str, n: int):
    """The benchmark's mesh of ``n`` facets."""
    if terrain_name == "rough":
        from viewfactor_operator import terrain

        return terrain(n)
    from scale import scale_mesh

    return scale_mesh(n)


def measure(terrain_name: str, n: int, order: list[str]) -> dict:
    from crater_thermal import vfoperator as vo
    from crater_thermal.raytrace import RayTracer

    mesh = mesh_of(terrain_name, n)
    tracer = RayTracer(mesh)
    builds = {"off": [], "on": []}
    last = {}
    for mode in order:
        vo.OCCLUSION_PROOF = mode == "on"
        t0 = time.perf_counter()
        F = vo.compressed_view_factors(mesh, tracer)
        builds[mode].append({"build_s": time.perf_counter() - t0, "rays": int(F.stats["rays"])})
        last[mode] = F
        print(terrain_name, n, mode, builds[mode][-1], flush=True)
    vo.OCCLUSION_PROOF = True
    a, b = last["off"], last["on"]
    differ = [k for k in vo._COMPRESSED_ARRAYS if not np.array_equal(getattr(a, k), getattr(b, k))]
    mean = {k: float(np.mean([x["build_s"] for x in v])) for k, v in builds.items()}
    return {
        "terrain": terrain_name,
        "facets": int(mesh.n_facets),
        "builds": builds,
        "mean_build_s": mean,
        "speedup": mean["off"] / mean["on"],
        "ray_ratio": builds["on"][0]["rays"] / builds["off"][0]["rays"],
        "arrays_equal": not differ,
        "arrays_differing": differ,
        "nbytes": int(b.nbytes),
        "load_average": list(os.getloadavg()),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--terrain", nargs="+", default=["rough", "scale"], choices=["rough", "scale"])
    ap.add_argument("--sizes", type=int, nargs="+", default=[20_000, 100_000])
    ap.add_argument("--order", nargs="+", default=["off", "on", "on", "off"], choices=["off", "on"])
    ap.add_argument("--out", default=str(HERE / "results" / "occlusion_proof.json"))
    args = ap.parse_args(argv)
    if not {"off", "on"} <= set(args.order):
        ap.error("--order needs both off and on")
    res = {"tolerance": 1e-3, "order": args.order, "cpu_count": os.cpu_count(), "runs": []}
    for name in args.terrain:
        for n in args.sizes:
            res["runs"].append(measure(name, n, args.order))
            Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
