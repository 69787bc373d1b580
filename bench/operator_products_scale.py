"""Benchmark: the one-vector IR product of `bench/scale.py`'s operator at a given size (issue 24).

Run:  CRATER_THERMAL_CACHE=DIR PYTHONPATH=$PWD python bench/operator_products_scale.py --facets 1000000
                                                          [--repeat 5] [--out FILE]

The generator crater of ``bench/scale.py`` (10 km, 5 km surround, 86 S) at ``--facets``; its operator as a
run gets it (``vfoperator.view_factor_operator`` with the view-factor cache of ``$CRATER_THERMAL_CACHE``:
read back from a kept build, or built), then ``--repeat`` products with one random vector (the coupled
record's product, every ``ir_product_samples`` steps). Writes the read or build time [s], the operator's
bytes in memory and each product's seconds as JSON (default ``bench/results/operator_products_scale.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale import scale_mesh  # noqa: E402

from crater_thermal import vfoperator  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--facets", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "operator_products_scale.json"))
    args = ap.parse_args()
    cache = os.environ.get("CRATER_THERMAL_CACHE")
    mesh = scale_mesh(args.facets)
    t0 = time.perf_counter()
    F = vfoperator.view_factor_operator(mesh, cache_dir=None if cache is None else Path(cache) / "viewfactors")
    get_s = time.perf_counter() - t0
    x = np.random.default_rng(0).random(mesh.n_facets)
    products = []
    for _ in range(args.repeat):
        t = time.perf_counter()
        F @ x
        products.append(time.perf_counter() - t)
    out = {
        "benchmark": "operator_products_scale",
        "facets": mesh.n_facets,
        "operator_get_s": get_s,
        "operator_nbytes": int(F.nbytes),
        "matvec_s": products,
        "gb_per_s": F.nbytes / min(products) / 1e9,
        "loadavg": os.getloadavg(),
        "cpus": os.cpu_count(),
    }
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
