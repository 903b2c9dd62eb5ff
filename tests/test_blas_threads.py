"""calibration.blas_threads: one BLAS thread inside the block, the previous limit after it."""

from __future__ import annotations

import json
import os
import subprocess
import sys

PROBE = """
import json
import numpy, scipy.linalg  # both OpenBLAS libraries loaded
from threadpoolctl import threadpool_info
from calibration.blas_threads import single_blas_thread

def threads():
    return sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})

before = threads()
with single_blas_thread():
    inside = threads()
after = threads()
single_blas_thread()  # dropped: the limit stays, as in a worker's initializer
print(json.dumps({"before": before, "inside": inside, "after": after, "kept": threads()}))
"""


def test_one_blas_thread_in_the_block_and_the_previous_limit_after_it() -> None:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2"}
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    seen = json.loads(out.stdout)
    assert seen["before"] == [2]
    assert seen["inside"] == [1]
    assert seen["after"] == [2]
    assert seen["kept"] == [1]
