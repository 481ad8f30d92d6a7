"""How busy the rest of the machine was while something was timed (for benchmark scripts).

Contract: ``with CpuMonitor() as m: ...`` sets ``m.other_cores`` to the CPU time that *other*
processes used during the block, in cores (machine-wide busy time from ``/proc/stat`` minus
this process's and its waited-for children's CPU time, divided by the wall time), or None
where ``/proc/stat`` is unavailable. On a 2-core machine anything above ~0.1 means the timing
was taken on a shared, busy machine and its figures are low.
"""
from __future__ import annotations

import os
import resource
import time
from pathlib import Path


class CpuMonitor:
    """CPU used by other processes during a ``with`` block, in cores (see module docstring)."""

    def __enter__(self) -> "CpuMonitor":
        self.other_cores: float | None = None
        self.wall_s: float = 0.0
        self._busy0, self._own0, self._t0 = machine_busy_seconds(), own_cpu_seconds(True), time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        busy1, own1 = machine_busy_seconds(), own_cpu_seconds(True)
        self.wall_s = time.perf_counter() - self._t0
        if self._busy0 is not None and busy1 is not None and self.wall_s > 0:
            self.other_cores = max(0.0, (busy1 - self._busy0 - (own1 - self._own0)) / self.wall_s)


def machine_busy_seconds() -> float | None:
    """CPU seconds the whole machine has been busy since boot (all cores, ``/proc/stat``); None
    where that file cannot be read."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
        user, nice, system, _idle, _iowait, irq, softirq, steal = (int(v) for v in fields[:8])
    except (OSError, ValueError, IndexError):
        return None
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def own_cpu_seconds(children: bool = False) -> float:
    """CPU seconds this process has used (all its threads), and with ``children`` those of the
    child processes it has waited for."""
    who = (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN) if children else (resource.RUSAGE_SELF,)
    return sum(u.ru_utime + u.ru_stime for u in map(resource.getrusage, who))
