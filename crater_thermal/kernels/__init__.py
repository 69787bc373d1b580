"""Numba kernels. Imports only numpy and numba; no I/O, no raising: kernels return status codes."""
