"""crater_thermal: thermal environment of lunar polar craters.

Data flow: case -> geometry -> fluxes -> temperatures -> analysis -> report.
SI units inside; named units (``lat_deg``, ``diameter_km``) only at the edges.
"""

__version__ = "0.1.0"
