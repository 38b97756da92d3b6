"""The commands' work on top of every layer: a rendered run (``pipeline``), grids of
configurations (``grid`` defines them, ``sweep`` runs them on local processes or Dask,
``sweep_stats`` sums them up), a user's real capture (``capture``, its command-line board
description in ``capture_options``), another tool's calibration scored (``exchange``), and the
process pool's set-up (``workers``).
"""
