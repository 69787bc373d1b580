"""Numba kernels of the direct sunlight (:mod:`crater_thermal.illumination` wraps them).

Only numpy and numba are imported here; no I/O, no raising.
"""

import numpy as np
from numba import njit


@njit(cache=True)
def ray_candidates(dirs, normals, weights, origins32, above_all, block):
    """Rays worth tracing in one batch of time steps.

    For every (patch direction ``k = step * m + j``, facet ``f``) with ``n_f . d_k > 0``
    the contribution ``w_j cos i`` goes to the flat cell ``step * nf + f`` of
    ``block`` directly when the ray is known to escape (origin above the whole
    mesh, pointing up); otherwise the ray is returned for tracing: its cell,
    weight, float32 origin and direction.
    """
    nk = dirs.shape[0]
    nf = normals.shape[0]
    m = weights.shape[0]
    count = 0
    for k in range(nk):
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        for f in range(nf):
            if normals[f, 0] * dx + normals[f, 1] * dy + normals[f, 2] * dz > 0.0:
                if not (above_all[f] and dz > 0.0):
                    count += 1
    cell = np.empty(count, np.int64)
    wcos = np.empty(count, np.float64)
    ray_org = np.empty((count, 3), np.float32)
    ray_dir = np.empty((count, 3), np.float32)
    i = 0
    for k in range(nk):
        dx, dy, dz = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        step = k // m
        w = weights[k - step * m]
        for f in range(nf):
            c = normals[f, 0] * dx + normals[f, 1] * dy + normals[f, 2] * dz
            if c > 0.0:
                if above_all[f] and dz > 0.0:
                    block[step * nf + f] += w * c
                    continue
                cell[i] = step * nf + f
                wcos[i] = w * c
                ray_org[i, 0] = origins32[f, 0]
                ray_org[i, 1] = origins32[f, 1]
                ray_org[i, 2] = origins32[f, 2]
                ray_dir[i, 0] = dx
                ray_dir[i, 1] = dy
                ray_dir[i, 2] = dz
                i += 1
    return cell, wcos, ray_org, ray_dir


@njit(cache=True)
def accumulate_visible(block, cell, wcos, visible):
    for i in range(cell.shape[0]):
        if visible[i]:
            block[cell[i]] += wcos[i]
