"""A rough synthetic site for horizon tests and benchmarks: a crater in self-affine random terrain.

Height field on a square grid (two triangles per cell, normals up): a Table 7.1-like simple crater
(bowl with a raised rim) plus a random surface with a power-law spectrum (Hurst exponent 0.8, RMS
slope ~12 deg at the grid scale, the order of lunar highland roughness at 50-100 m baselines), from
a fixed seed.  Nothing here is a physics reference; it is only meant to have many small hills that
cast and receive shadows at all azimuths.
"""

from __future__ import annotations

import math

import numpy as np

from crater_thermal.geometry import Mesh


def rough_site(
    n_facets: int = 2000,
    size_m: float = 6000.0,
    crater_diameter_m: float = 3000.0,
    rms_slope_deg: float = 12.0,
    seed: int = 7,
) -> Mesh:
    """Mesh of ``2 n^2 ~ n_facets`` facets over a ``size_m`` square centred on the origin [m]."""
    n = max(4, int(round(math.sqrt(n_facets / 2.0))))
    xs = np.linspace(-0.5 * size_m, 0.5 * size_m, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="xy")
    r = np.hypot(X, Y) / (0.5 * crater_diameter_m)
    depth = 0.2 * crater_diameter_m
    rim = 0.04 * crater_diameter_m
    z = np.where(r < 1.0, (rim + depth) * r**2 - depth, rim * np.exp(-(((r - 1.0) / 0.35) ** 2)))
    # self-affine roughness: spectral synthesis, amplitude ~ k^-(1 + H)
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(n + 1)
    K = np.hypot(*np.meshgrid(k, k, indexing="xy"))
    K[0, 0] = np.inf
    amp = K ** -(1.0 + 0.8)
    field = np.real(np.fft.ifft2(amp * np.exp(2j * np.pi * rng.random(K.shape))))
    dx = xs[1] - xs[0]
    gy, gx = np.gradient(field, dx)
    field *= math.tan(math.radians(rms_slope_deg)) / math.sqrt(np.mean(gx**2 + gy**2))
    Z = z + field
    V = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    idx = np.arange(V.shape[0]).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(V, F, {"kind": "file", "source": "rough_site", "size_m": size_m, "seed": seed})
