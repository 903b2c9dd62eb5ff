"""Freed array memory kept for reuse (:mod:`calibration.heap_reuse`), measured by the kernel's
count of page faults in a fresh process: with glibc's defaults a 40 MB temporary is mapped
from the kernel and unmapped on every allocation (its pages fault in again each time), once
the thresholds are raised it is served from the heap it was freed to."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from calibration.heap_reuse import MMAP_THRESHOLD_BYTES, reuse_freed_memory

_ALLOCATE = textwrap.dedent(
    """
    import resource, sys
    import numpy as np
    from calibration.heap_reuse import reuse_freed_memory
    if sys.argv[1] == "reuse":
        assert reuse_freed_memory() and reuse_freed_memory()
    a = np.ones(5_000_000); del a  # 40 MB
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        a = np.ones(5_000_000); del a
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """
)


def _page_faults(mode: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", _ALLOCATE, mode], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    return int(done.stdout.split()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_freed_temporary_is_reused_without_faulting_its_pages_in_again() -> None:
    assert 40e6 < MMAP_THRESHOLD_BYTES  # the temporary is below the raised threshold
    assert reuse_freed_memory() is True  # glibc on Linux takes the settings
    assert reuse_freed_memory() is True  # and a second call changes nothing
    default, reused = _page_faults("default"), _page_faults("reuse")
    assert default >= 20 * 19  # at least one fault per 2 MB page of every allocation
    assert reused <= default // 100
