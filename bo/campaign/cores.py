"""Cores shared by the worker processes of one machine: a stage's last runs take the idle cores.

Contract
--------
A campaign on a local dask cluster runs ``cores`` one-thread worker processes, one DEM batch each.
When a stage has fewer batches left than workers (the last run of five verification replicates on
two workers, the slowest run of a surrogate round), the other workers sit idle while the stage waits
for that run. A :class:`CoreShare` is a small file through which the campaign process tells its
workers how many batches are in flight, so that a running batch can take the idle cores:

* campaign side, :meth:`CoreShare.publish(busy)`: the number of batches in flight, written
  atomically (``os.replace``) each time it changes;
* worker side, :meth:`CoreShare.threads`: ``max(1, cores // busy)``, the threads a batch may use
  now; 1 when the file is missing or unreadable (a worker never fails for the share's sake);
* :class:`ThreadFollower` (a batch's ``threads`` callable, asked every load-cell sample of a draw
  down run, :meth:`torchdem.drawdown.DrawDownTest.run_members`): reads the file at most every
  ``period_s`` seconds of wall time, caps its answer by the cores that other processes left idle
  over that period, and returns the latest answer.

The DEM kernels give the same bits on any number of threads (``torchdem/_ext``), and the draw down
KPIs too (``tests/test_cores.py``), so a run that changes its threads mid-way reports what it would
have reported on one. Every batch starts from the share's current answer, so a worker that ran a
stage's tail on two threads goes back to one when the next stage fills the cluster again.
"""
from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from torchdem.cpu_monitor import machine_busy_seconds, own_cpu_seconds
from torchdem.errors import out_of_range

__all__ = ["CoreShare", "ThreadFollower", "local_cores"]


def local_cores(n_workers: int | None) -> int:
    """The cores a local cluster of ``n_workers`` one-thread workers shares (None: one per core):
    its workers, but no more than the machine has. More workers than cores time-slice the machine's
    cores, and a stage's last batch may still take no more than those."""
    machine = os.cpu_count() or 1
    return min(n_workers or machine, machine)


@dataclass(frozen=True)
class CoreShare:
    """The core-share file of one local cluster.

    Attributes:
        path: the file (a decimal count of batches in flight); workers on the same machine read it.
        cores: cores the cluster may use in all (its worker processes, one thread each).
    """

    path: str
    cores: int

    def __post_init__(self):
        if isinstance(self.cores, bool) or not isinstance(self.cores, int) or self.cores < 1:
            raise out_of_range("cores", self.cores, "an int >= 1", "CoreShare")

    @classmethod
    def create(cls, cores: int, directory: str | None = None) -> CoreShare:
        """A fresh share file (in the system's temporary directory unless ``directory``), no batch
        in flight yet."""
        fd, path = tempfile.mkstemp(prefix="torchdem-cores-", suffix=".txt", dir=directory)
        os.close(fd)
        share = cls(path, cores)
        share.publish(0)
        return share

    def publish(self, busy: int) -> None:
        """Campaign side: ``busy`` batches are in flight now."""
        if isinstance(busy, bool) or not isinstance(busy, int) or busy < 0:
            raise out_of_range("busy", busy, "an int >= 0", "CoreShare.publish")
        tmp = f"{self.path}.{os.getpid()}.tmp"
        with open(tmp, "w") as fh:
            fh.write(str(busy))
        os.replace(tmp, self.path)

    def busy(self) -> int | None:
        """The batches in flight, as last published; None when the file cannot be read."""
        try:
            with open(self.path) as fh:
                return max(0, int(fh.read().strip()))
        except (OSError, ValueError):
            return None

    def threads(self) -> int:
        """Worker side: threads a running batch may use now, ``max(1, cores // busy)``."""
        busy = self.busy()
        return 1 if busy is None else max(1, self.cores // max(1, busy))

    def remove(self) -> None:
        """Delete the file (the executor that created it closes)."""
        Path(self.path).unlink(missing_ok=True)


@dataclass
class ThreadFollower:
    """``() -> int``: the threads a running batch may use, decided at most every ``period_s`` s of
    wall time: the share's answer, but no more than the cores other processes left free over the
    last period (``/proc/stat``'s busy time less this process's own). The share alone would
    oversubscribe a machine where something else runs beside the campaign (a test suite): a
    two-thread run whose second core is taken waits at every parallel region, and a mini-box run
    took 24 s instead of 6. The first answer is 1 (no period measured yet); where ``/proc/stat``
    cannot be read, the share's answer stands alone."""

    share: CoreShare
    period_s: float = 1.0
    machine_cores: int = field(default_factory=lambda: os.cpu_count() or 1)
    _last: float = field(default=-float("inf"), repr=False)
    _busy: float | None = field(default=None, repr=False)
    _own: float = field(default=0.0, repr=False)
    _threads: int = field(default=1, repr=False)

    def __call__(self) -> int:
        now = time.monotonic()
        if now - self._last < self.period_s:
            return self._threads
        busy, own = machine_busy_seconds(), own_cpu_seconds()
        allowed = self.share.threads()
        if busy is not None:
            if self._busy is None:
                allowed = 1
            else:
                others = max(0.0, (busy - self._busy) - (own - self._own)) / max(now - self._last, 1e-9)
                allowed = max(1, min(allowed, int(self.machine_cores - others + 0.5)))
        self._last, self._busy, self._own, self._threads = now, busy, own, allowed
        return allowed
