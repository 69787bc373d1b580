"""Numba kernels: every ``@njit`` function of crater_thermal lives here (poliastro's core/wrapper split).

Modules import only numpy, numba and the standard library's math; no I/O, no raising: kernels return
status codes or flags, and the wrapping physics module turns them into exceptions.

* :mod:`~crater_thermal.kernels.conduction`: 1-D nonlinear heat conduction (wrapped by ``thermal``);
* :mod:`~crater_thermal.kernels.viewfactors`: view-factor quadrature and sparse assembly (``viewfactors``);
* :mod:`~crater_thermal.kernels.illumination`: direct-sunlight ray candidates (``illumination``);
* :mod:`~crater_thermal.kernels.horizons`: horizon bisection, disk-segment tables and the per-step
  direct flux from horizon maps (``horizons``).
"""
