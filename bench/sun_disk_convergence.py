"""Convergence of the sampled solar disk (illumination.sun_disk) against a much finer disk.

Two grazing-light cases, Sun at 1 au, S = 1 (fluxes are fractions of S):
  self   - a facet's own plane cuts the disk (Sun centre swept from 1.1 disk radii below to
           1.1 above the facet plane; facet tilts 0, 0.3, 1 rad). Error in units of S sin(alpha),
           the largest flux such a facet gets while the disk straddles its plane.
  terrain - a facet facing the Sun, a horizontal terrain horizon sweeping across the disk
           (7 orientations of the sampling grid). Error of the visible fraction, exact value by
           quadrature (illumination.disk_fraction_above).
Prints one JSON object per (law, n_rings).

    PYTHONPATH=$PWD python bench/sun_disk_convergence.py
"""

import json

import numpy as np

from crater_thermal import illumination as il
from crater_thermal.constants import AU, SUN_RADIUS

ALPHA = np.arcsin(SUN_RADIUS / AU)


class _Facet:
    def __init__(self, n):
        self.normals = np.atleast_2d(n)
        self.vertices = np.array([[0.0, 0.0, 1e9]])


class _Tracer:
    def __init__(self, terrain):
        self.terrain = terrain

    def facet_origins(self, i):
        return np.zeros((len(i), 3))

    def occluded(self, o, d):
        return d[:, 2] < 0 if self.terrain else np.zeros(len(o), bool)


def self_shadow(disk):
    out = []
    for tilt in (0.0, 0.3, 1.0):
        g = np.linspace(-1.1 * ALPHA, 1.1 * ALPHA, 201)
        el = g - tilt
        s = np.stack([np.zeros_like(el), -np.cos(el), np.sin(el)], 1)
        out.append(
            il.direct_irradiance(
                _Facet([0, -np.sin(tilt), np.cos(tilt)]), _Tracer(False), s, np.full(g.size, AU), 1.0, disk
            )[:, 0]
        )
    return np.concatenate(out)


def terrain(disk, law):
    errs = []
    h = np.linspace(-1.05, 1.05, 211)
    s = np.stack([np.zeros_like(h), -np.cos(h * ALPHA), np.sin(h * ALPHA)], 1)
    exact = np.array([il.disk_fraction_above(law, -x) for x in h]) * np.cos(h * ALPHA)
    for rot in np.deg2rad([0, 7, 15, 30, 45, 60, 90]):
        c, sn = np.cos(rot), np.sin(rot)
        d2 = il.SunDisk(disk.offsets @ np.array([[c, sn], [-sn, c]]), disk.weights, disk.law, disk.n_rings)
        E = il.direct_irradiance(_Facet([0, -1.0, 0]), _Tracer(True), s, np.full(h.size, AU), 1.0, d2)[:, 0]
        errs.append(np.abs(E - exact))
    errs = np.concatenate(errs)
    return float(errs.max()), float(errs.mean())


def main():
    for law in sorted(il.LIMB_DARKENING_LAWS):
        ref = self_shadow(il.sun_disk(60, law))
        for n in (1, 2, 3, 4, 5, 6, 8, 12):
            disk = il.sun_disk(n, law)
            e = np.abs(self_shadow(disk) - ref) / np.sin(ALPHA)
            tmax, tmean = terrain(disk, law)
            print(
                json.dumps(
                    {
                        "law": law,
                        "n_rings": n,
                        "patches": disk.n_patches,
                        "self_shadow_max_err_of_S_sin_alpha": round(float(e.max()), 5),
                        "terrain_fraction_max_err": round(tmax, 5),
                        "terrain_fraction_mean_err": round(tmean, 5),
                    }
                )
            )


if __name__ == "__main__":
    main()
