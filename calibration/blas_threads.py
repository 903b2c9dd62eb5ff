"""One BLAS thread per process while calibrating.

The pipeline is parallel over frames, one process per core
(:func:`calibration.pipeline.calibrate_archive`, the station's analysis pool),
and its numerical work is many small products and solves (a 3×3 system per
edge profile, a few dozen bins per row). A BLAS thread pool on top of that
parallelism does not speed anything up: each small call hands work to helper
threads that the other processes' work keeps off the cores, and waits for them.
Measured on 2 cores with the other core busy, the whole-sweep defocus fit ran
2.1× slower with OpenBLAS's default 2 threads than with 1 (3.3 s against 1.6 s;
3.5× in the test suite, >10× on a busier machine), and a 100-frame calibration
on idle cores 1 s faster with 1 thread.

:func:`single_blas_thread` limits every BLAS library loaded in the process
(numpy's and scipy's OpenBLAS, MKL, BLIS) and OpenMP to one thread, for a block
or, from a worker process's initializer, for the process's life.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Any

import numpy  # noqa: F401  (loaded first: threadpoolctl limits only the libraries loaded)
import scipy.linalg  # noqa: F401  (scipy's own OpenBLAS)
from threadpoolctl import threadpool_limits


def single_blas_thread() -> AbstractContextManager[Any]:
    """Limit BLAS and OpenMP thread pools to one thread: use as ``with single_blas_thread():``
    for a block (the previous limits come back on exit), or call it once in a worker process
    whose whole life is numerical work and drop the returned object (the limit then stays)."""
    return threadpool_limits(limits=1)
