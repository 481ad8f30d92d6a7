"""torchdem.heap: freed memory stays in the process, as dask's workers need.

Each case runs in its own interpreter (the thresholds are process-wide), with dask's worker
environment ``MALLOC_TRIM_THRESHOLD_=65536``: a 1 MiB block allocated, written and freed ten
times. Without :func:`torchdem.heap.keep_freed_memory` glibc hands the block back after every
free and all 256 pages fault again each time (2,560 faults measured); with it, none should.
"""
import os
import platform
import subprocess
import sys

import pytest

PROBE = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from torchdem.heap import keep_freed_memory
    assert keep_freed_memory()
def touch():
    block = np.empty(1 << 17)          # 1 MiB of float64
    block.fill(1.0)
    return float(block[-1])
touch()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    touch()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
PAGES = 10 * (1 << 20) // 4096


def _faults(mode: str, **env: str) -> int:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True,
                         env={**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536", **env})
    return int(out.stdout.split()[-1])


glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt thresholds are glibc's")


@glibc
def test_freed_blocks_are_reused_without_page_faults_under_dasks_trim_threshold():
    assert _faults("plain") > 0.5 * PAGES      # the probe sees the faults it is meant to remove
    assert _faults("keep") < 0.02 * PAGES


@glibc
def test_keep_heap_can_be_switched_off():
    code = "from torchdem.heap import keep_freed_memory; print(keep_freed_memory())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "TORCHDEM_KEEP_HEAP": "0"})
    assert out.stdout.strip() == "False"
