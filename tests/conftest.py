"""Suite-wide settings: one BLAS thread per test process.

The suite runs on 2 cores in 2 xdist workers that start servers and analysis
processes of their own; BLAS thread pools on top of that made the whole-sweep
defocus fit 3.5× slower here and past the 300 s timeout on a busier CI machine
(see :mod:`calibration.blas_threads`). ``make test`` also sets the environment
variables for the processes the tests start.
"""

from __future__ import annotations

import os

import pytest

from calibration.blas_threads import single_blas_thread

_BLAS_LIMIT = single_blas_thread()  # for this process's life


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """One line on the machine the suite ran on: the CPUs it may use and the BLAS threads."""
    from threadpoolctl import threadpool_info

    blas = sorted({f"{i['internal_api']} {i['num_threads']}" for i in threadpool_info()})
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
    terminalreporter.write_line(
        f"machine: {os.cpu_count()} CPUs, {usable} usable by this process, "
        f"load average {os.getloadavg()[0]:.1f}; BLAS threads {', '.join(blas)}"
    )
