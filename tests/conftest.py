"""Test-session settings.

One BLAS thread: scipy's sparse least-squares issues many small threaded dot products, which
stall when the machine is busier than its cores; tests measure numbers, not speed.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
