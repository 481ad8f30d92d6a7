"""Executors: run batches of DEM evaluations here or on a dask cluster, and the store glue.

Contract
--------
A DEM evaluation is ``(params, seed, condition) -> KPIs``. The unit of work handed to user
code is a *batch*: ``evaluate_batch(tasks: list[EvalTask]) -> list[EvalOutcome]``, one outcome
per task, in the same order. A batched DEM ensemble runs all tasks of a batch as one tensor
program (leading axis ``B`` = the batch), so every batch an executor builds holds tasks of a
**single condition** (the mixture, hence the particle population, is shared by the ensemble);
tasks are grouped by condition in first-seen order and cut into chunks of at most
``batch_size`` (``make_batches``).

* ``EvalTask(params, seed, condition, task_id)``: frozen; ``params`` is a ``dict`` name ->
  finite float with keys in sorted order (treat it as read-only); ``task_id`` is the store's
  row id (``None`` for tasks that never saw a store).
* ``EvalOutcome(kpis, error, wall_time)``: frozen; exactly one of ``kpis`` (dict name ->
  float) and ``error`` (message) is set; ``wall_time`` in seconds is what the evaluation cost
  (for an ensemble member: the wall time of its batch). Build with ``EvalOutcome.success`` /
  ``EvalOutcome.failure``.
* ``Executor.run(tasks)`` yields one ``list[(EvalTask, EvalOutcome)]`` per batch *as batches
  finish* (not necessarily in submission order). If ``evaluate_batch`` raises or returns the
  wrong number of outcomes, every task of that batch gets a failure outcome that says so; the
  executor itself does not raise for a bad evaluation, so one blown-up batch does not cost
  the others. ``Executor.run_stream(batches)`` takes the batches from an iterable as workers free
  up (the dask executor keeps ``parallelism`` in flight; in process, one after the other).
* ``InProcessExecutor(evaluate_batch, batch_size)``: runs the batches one after the other in
  this process. This is where a batched DEM ensemble normally runs (one process owns the
  CPU/GPU threads).
* ``DaskExecutor(evaluate_batch, batch_size, client=... | address=... | n_workers=...)``:
  submits every batch as a dask future and yields with ``as_completed``. Given ``client`` it
  uses (and never closes) that client; given ``address`` it connects to a running scheduler;
  otherwise it starts a ``LocalCluster`` of worker processes (one thread each; scheduler HTTP
  server / dashboard on a free port, ``client.dashboard_link``) and closes it in ``close()``.
  ``evaluate_batch`` is pickled to the workers, so it must be picklable *by reference*: a
  module-level function, or ``functools.partial`` of one with picklable arguments, works; a
  lambda or a function defined inside another function is pickled by value with its whole
  closure (which then must be picklable too, and is shipped with every batch) - avoid it.
  Workers import the function's module, so it must be importable there (installed package,
  or ``PYTHONPATH``).
  A batch whose worker dies (``KilledWorker``, lost connection) is reported as failed with
  the dask error; ``CampaignStore.reset_failed`` puts such tasks back in the queue.
  Given ``core_share`` (:class:`bo.campaign.cores.CoreShare`, for workers on this machine) it
  publishes the number of batches in flight each time it changes, after drawing the next batch,
  so that a stage's last batches take the cores of the workers that have none left
  (``bo.campaign.dem.evaluate_batch(core_share=...)``); it removes the share's file in ``close()``.
* ``run_pending(store, executor, stage=None)``: claims pending tasks from a
  ``bo.campaign.store.CampaignStore`` (one batch of one condition at a time, whenever a worker
  is free, under a lease that a background thread renews), runs them and writes
  each finished batch to the store in one transaction as soon as it finishes, so a kill loses
  at most the batches in flight (their leases go stale and the next run claims them again).
  With ``wait=True`` (default) it returns only when no task of ``stage`` is pending or running
  anywhere, i.e. after tasks claimed by other live processes have finished too; the results
  are then all in the store. Failed tasks are not retried (see ``reset_failed``).

Clusters with dask-jobqueue
---------------------------
dask-jobqueue is not a dependency; install it on the cluster (``pip install dask-jobqueue``).
Build the cluster in the (Hydra) entry point and hand a client to ``DaskExecutor``. A batched
ensemble parallelises *inside* the batch (torch threads), so give every job one single-thread
worker (one batch at a time) that books all the cores of the job::

    from dask.distributed import Client
    from dask_jobqueue import SLURMCluster          # PBSCluster: resource_spec="select=1:ncpus=8"

    cluster = SLURMCluster(cores=1, processes=1, job_cpu=8, memory="16GB",
                           walltime="04:00:00", job_extra_directives=["--gres=gpu:1"],
                           job_script_prologue=["source /path/to/torchdem/.venv/bin/activate"])
    cluster.scale(jobs=4)                          # or cluster.adapt(minimum_jobs=1, maximum_jobs=8)
    client = Client(cluster)
    client.wait_for_workers(4)
    executor = DaskExecutor(evaluate_batch, batch_size=16, client=client, max_in_flight=4)
    run_pending(store, executor, stage="round-3")

Dask's nanny sets ``OMP_NUM_THREADS=1`` for its workers, so call ``torch.set_num_threads(8)``
(the booked cores) inside ``evaluate_batch``. It also sets ``MALLOC_TRIM_THRESHOLD_=65536``, under
which a draw down run spent 20-25 % of its CPU time page-faulting freed memory back; every
:class:`torchdem.simulation.Simulation` raises the threshold again (:mod:`torchdem.heap`). With
an adaptive cluster the number of worker threads at start-up can be zero, hence ``max_in_flight``. Only the campaign process touches
the SQLite store (workers only evaluate), so the store file can stay on the submit host's
local disk; SQLite's WAL mode does not work on network file systems (NFS, Lustre).
"""
from __future__ import annotations

import logging
import math
import os
import threading
import time
import traceback
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from numbers import Integral, Real
from typing import TYPE_CHECKING

from torchdem.errors import ConfigError, out_of_range

if TYPE_CHECKING:  # bo.campaign.store imports this module; the glue only needs the type.
    from bo.campaign.cores import CoreShare
    from bo.campaign.store import CampaignStore

__all__ = [
    "EvalTask",
    "EvalOutcome",
    "EvaluateBatch",
    "FinishedBatch",
    "Executor",
    "InProcessExecutor",
    "DaskExecutor",
    "RunSummary",
    "make_batches",
    "evaluate_checked",
    "run_pending",
]


def canonical_params(params: Mapping[str, float], source: str) -> dict[str, float]:
    """Validated copy of a parameter set: str names, finite floats, keys in sorted order."""
    if not isinstance(params, Mapping):
        raise out_of_range("params", params, "a mapping of parameter name -> finite float", source)
    if len(params) == 0:
        raise out_of_range("params", dict(params), "at least one parameter", source)
    out: dict[str, float] = {}
    for name in sorted(params, key=str):
        value = params[name]
        if not isinstance(name, str) or not name:
            raise out_of_range("parameter name", name, "a non-empty str", source)
        if isinstance(value, bool) or not isinstance(value, Real):
            raise out_of_range(f"params[{name!r}]", value, "a finite real number", source)
        value = float(value)
        if not math.isfinite(value):
            raise out_of_range(f"params[{name!r}]", value, "a finite real number", source)
        out[name] = value
    return out


def _check_seed(seed, source: str) -> int:
    if isinstance(seed, bool) or not isinstance(seed, Integral):
        raise out_of_range("seed", seed, "an int", source)
    return int(seed)


def _check_condition(condition, source: str) -> str:
    if not isinstance(condition, str) or not condition:
        raise out_of_range("condition", condition, "a non-empty str such as '50-50'", source)
    return condition


@dataclass(frozen=True)
class EvalTask:
    """One DEM evaluation to run.

    Attributes:
        params: contact parameter set, name -> finite float (e.g. ``{"mu_s_pp": 0.49}``),
            keys sorted; read-only by convention.
        seed: random seed of the packing / particle generation.
        condition: experimental condition, e.g. the mixture ``"50-50"``.
        task_id: row id in the campaign store, ``None`` outside a store.
    """

    params: dict[str, float]
    seed: int
    condition: str
    task_id: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "params", canonical_params(self.params, "EvalTask"))
        object.__setattr__(self, "seed", _check_seed(self.seed, "EvalTask"))
        _check_condition(self.condition, "EvalTask")
        if self.task_id is not None:
            object.__setattr__(self, "task_id", _check_seed(self.task_id, "EvalTask.task_id"))

    def __hash__(self) -> int:  # dict field: hash its items (explicit __hash__ is kept)
        return hash((tuple(self.params.items()), self.seed, self.condition, self.task_id))

    @property
    def key(self) -> tuple[tuple[tuple[str, float], ...], int, str]:
        """``(params items, seed, condition)``: what makes two evaluations the same."""
        return tuple(self.params.items()), self.seed, self.condition


@dataclass(frozen=True)
class EvalOutcome:
    """Result of one evaluation: KPIs or an error message, and the wall time in seconds.

    Exactly one of ``kpis`` and ``error`` is not ``None``. KPI values are floats; a
    non-finite KPI is allowed (it is stored as null and read back as NaN).
    """

    kpis: dict[str, float] | None
    error: str | None
    wall_time: float

    def __post_init__(self):
        if (self.kpis is None) == (self.error is None):
            raise ConfigError(
                f"EvalOutcome: exactly one of kpis and error must be set; got kpis={self.kpis!r}, "
                f"error={self.error!r}")
        if self.kpis is not None:
            if not isinstance(self.kpis, Mapping):
                raise out_of_range("kpis", self.kpis, "a mapping of KPI name -> float", "EvalOutcome")
            kpis = {}
            for name in sorted(self.kpis, key=str):
                value = self.kpis[name]
                if not isinstance(name, str) or not name:
                    raise out_of_range("KPI name", name, "a non-empty str", "EvalOutcome")
                if isinstance(value, bool) or not isinstance(value, Real):
                    raise out_of_range(f"kpis[{name!r}]", value, "a real number", "EvalOutcome")
                kpis[name] = float(value)
            object.__setattr__(self, "kpis", kpis)
        elif not isinstance(self.error, str):
            raise out_of_range("error", self.error, "a str message", "EvalOutcome")
        if isinstance(self.wall_time, bool) or not isinstance(self.wall_time, Real) \
                or not math.isfinite(self.wall_time) or self.wall_time < 0:
            raise out_of_range("wall_time", self.wall_time, "a finite number of seconds >= 0",
                               "EvalOutcome")
        object.__setattr__(self, "wall_time", float(self.wall_time))

    @property
    def ok(self) -> bool:
        return self.error is None

    @classmethod
    def success(cls, kpis: Mapping[str, float], wall_time: float) -> EvalOutcome:
        return cls(dict(kpis), None, wall_time)

    @classmethod
    def failure(cls, error: str, wall_time: float = 0.0) -> EvalOutcome:
        return cls(None, str(error), wall_time)


EvaluateBatch = Callable[[list[EvalTask]], list[EvalOutcome]]
FinishedBatch = list[tuple[EvalTask, EvalOutcome]]


def _positive_int(value, name: str, source: str) -> int:
    if isinstance(value, bool) or not isinstance(value, Integral) or value < 1:
        raise out_of_range(name, value, "an int >= 1", source)
    return int(value)


def _check_batch_size(batch_size, source: str) -> int:
    return _positive_int(batch_size, "batch_size", source)


def make_batches(tasks: Iterable[EvalTask], batch_size: int) -> list[list[EvalTask]]:
    """Group tasks by condition (first-seen order, task order kept) into chunks <= batch_size."""
    batch_size = _check_batch_size(batch_size, "make_batches")
    by_condition: dict[str, list[EvalTask]] = {}
    for task in tasks:
        if not isinstance(task, EvalTask):
            raise out_of_range("task", task, "an EvalTask", "make_batches")
        by_condition.setdefault(task.condition, []).append(task)
    return [group[i:i + batch_size]
            for group in by_condition.values() for i in range(0, len(group), batch_size)]


def evaluate_checked(evaluate_batch: EvaluateBatch, tasks: list[EvalTask]) -> list[EvalOutcome]:
    """Call ``evaluate_batch(tasks)`` and turn an exception or a malformed answer into failures.

    Module-level so dask can ship it to workers. Always returns one outcome per task.
    """
    start = time.perf_counter()
    try:
        outcomes = evaluate_batch(list(tasks))
    except Exception as exc:  # one bad batch must not stop the campaign
        wall = time.perf_counter() - start
        tb = traceback.format_exception_only(type(exc), exc)[-1].strip()
        return [EvalOutcome.failure(f"evaluate_batch raised {tb}", wall) for _ in tasks]
    wall = time.perf_counter() - start
    if not isinstance(outcomes, Sequence) or len(outcomes) != len(tasks) \
            or not all(isinstance(o, EvalOutcome) for o in outcomes):
        got = (f"{len(outcomes)} items" if isinstance(outcomes, Sequence)
               else type(outcomes).__name__)
        return [EvalOutcome.failure(
            f"evaluate_batch returned {got}; expected a list of {len(tasks)} EvalOutcome "
            f"(one per task, same order)", wall) for _ in tasks]
    return list(outcomes)


class Executor(ABC):
    """Runs batches of ``EvalTask`` through ``evaluate_batch``; see the module docstring."""

    def __init__(self, evaluate_batch: EvaluateBatch, batch_size: int,
                 affinity: Callable[[Mapping[str, float]], tuple] | None = None):
        if not callable(evaluate_batch):
            raise out_of_range("evaluate_batch", evaluate_batch,
                               "a callable list[EvalTask] -> list[EvalOutcome]", type(self).__name__)
        if affinity is not None and not callable(affinity):
            raise out_of_range("affinity", affinity, "a callable params -> tuple, or None", type(self).__name__)
        self.evaluate_batch = evaluate_batch
        self.batch_size = _check_batch_size(batch_size, type(self).__name__)
        self.affinity = affinity  # run_pending batches tasks of equal affinity together (CampaignStore.claim)

    @property
    @abstractmethod
    def parallelism(self) -> int:
        """How many batches can run at the same time (>= 1)."""

    @abstractmethod
    def run(self, tasks: Sequence[EvalTask]) -> Iterator[FinishedBatch]:
        """Yield ``[(task, outcome), ...]`` for each batch as it finishes."""

    def run_stream(self, batches: Iterable[list[EvalTask]]) -> Iterator[FinishedBatch]:
        """Run batches drawn from ``batches`` one by one as workers free up, yielding each as it
        finishes; a new batch is drawn only after the consumer has taken a finished one (here:
        one after the other)."""
        for batch in batches:
            yield from self.run(batch)

    def close(self) -> None:
        """Release resources this executor created (not those it was given)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class InProcessExecutor(Executor):
    """Runs the batches one after the other in this process (the default)."""

    @property
    def parallelism(self) -> int:
        return 1

    def run(self, tasks: Sequence[EvalTask]) -> Iterator[FinishedBatch]:
        for batch in make_batches(tasks, self.batch_size):
            yield list(zip(batch, evaluate_checked(self.evaluate_batch, batch)))


def local_cluster(n_workers: int | None = None, cluster_kwargs: Mapping | None = None):
    """The ``LocalCluster`` a :class:`DaskExecutor` starts: ``n_workers`` processes (default
    ``os.cpu_count()``) of one thread each, the dashboard on a free port; ``cluster_kwargs`` override.

    dask's ``distributed`` logger is set to WARNING first: it logs at INFO every scheduler, nanny,
    worker and connection that comes and goes, and the CLIs' Hydra logging prints INFO, so a
    campaign's own lines were lost among some 35 of dask's. Its warnings and errors still show.
    A cluster or client the user gives (``address``, ``client``) keeps its logging."""
    from dask.distributed import LocalCluster  # optional at import time

    logging.getLogger("distributed").setLevel(logging.WARNING)
    kwargs = {"n_workers": n_workers or os.cpu_count() or 1, "threads_per_worker": 1,
              "processes": True, "dashboard_address": ":0"}  # a free port, never 8787
    kwargs.update(cluster_kwargs or {})
    return LocalCluster(**kwargs)


class DaskExecutor(Executor):
    """Runs the batches as dask.distributed futures; see the module docstring.

    Args:
        evaluate_batch: picklable by reference (module-level function or partial of one).
        batch_size: tasks per batch, >= 1.
        client: an existing ``distributed.Client``; used as is, never closed here.
        address: scheduler address (``"tcp://host:8786"``) to connect to when no client given.
        n_workers: worker processes of the ``LocalCluster`` started when neither client nor
            address is given (default ``os.cpu_count()``); one thread each.
        max_in_flight: batches ``run_pending`` keeps in flight; default the number of worker
            threads at construction (at least 1).
        cluster_kwargs: extra ``LocalCluster`` arguments (e.g. ``dashboard_address=":8787"``,
            ``memory_limit="8GB"``).
        core_share: where to publish the batches in flight for the workers (module docstring);
            its file is removed in ``close()``.
    """

    def __init__(self, evaluate_batch: EvaluateBatch, batch_size: int, *, client=None,
                 address: str | None = None, n_workers: int | None = None,
                 max_in_flight: int | None = None, cluster_kwargs: Mapping | None = None,
                 affinity: Callable[[Mapping[str, float]], tuple] | None = None,
                 core_share: CoreShare | None = None):
        super().__init__(evaluate_batch, batch_size, affinity)
        self.core_share = core_share
        from dask.distributed import Client  # optional at import time

        if client is not None and address is not None:
            raise ConfigError("DaskExecutor: give either client or address, not both "
                              f"(client={client!r}, address={address!r})")
        if n_workers is not None:
            n_workers = _positive_int(n_workers, "n_workers", "DaskExecutor")
        if max_in_flight is not None:
            max_in_flight = _positive_int(max_in_flight, "max_in_flight", "DaskExecutor")
        self._own_client = client is None
        self._cluster = None
        if client is not None:
            self.client = client
        elif address is not None:
            self.client = Client(address)
        else:
            self._cluster = local_cluster(n_workers, cluster_kwargs)
            try:
                self.client = Client(self._cluster)
            except BaseException:
                self._cluster.close()
                raise
        if max_in_flight is None:
            max_in_flight = max(1, sum(self.client.nthreads().values()))
        self._max_in_flight = max_in_flight

    @property
    def parallelism(self) -> int:
        return self._max_in_flight

    def run(self, tasks: Sequence[EvalTask]) -> Iterator[FinishedBatch]:
        batches = make_batches(tasks, self.batch_size)
        return self._stream(batches, max(1, len(batches)))  # every batch submitted at once

    def run_stream(self, batches: Iterable[list[EvalTask]]) -> Iterator[FinishedBatch]:
        """Keep ``parallelism`` batches in flight: each time one finishes (and has been taken),
        the next is drawn from ``batches`` and submitted, so a worker that finishes a short batch
        does not wait for a long one elsewhere."""
        return self._stream(batches, self.parallelism)

    def _stream(self, batches: Iterable[list[EvalTask]], max_in_flight: int) -> Iterator[FinishedBatch]:
        from dask.distributed import as_completed

        source = iter(batches)
        running = as_completed()
        # Only batches not yet taken are held: a finished batch's future is released once its
        # outcomes are read, since the scheduler recomputes every held result a lost worker had
        # (a worker restarted after missed heartbeats would rerun hours of finished DEM runs).
        in_flight: dict[str, tuple[object, list[EvalTask]]] = {}

        def submit_next() -> None:
            batch = next(source, None)
            if batch:
                future = self.client.submit(evaluate_checked, self.evaluate_batch, list(batch), pure=False)
                in_flight[future.key] = (future, list(batch))
                running.add(future)

        def publish(busy: int) -> None:
            if self.core_share is not None:
                self.core_share.publish(busy)

        publish(max_in_flight)  # a first batch must not take the cores of those still being drawn
        for _ in range(max_in_flight):
            submit_next()
        publish(len(in_flight))
        try:
            for future in running:
                _, batch = in_flight.pop(future.key)
                try:
                    outcomes = future.result()
                except Exception as exc:  # worker died, connection lost, unpicklable function
                    msg = traceback.format_exception_only(type(exc), exc)[-1].strip()
                    outcomes = [EvalOutcome.failure(f"dask could not run the batch: {msg}") for _ in batch]
                future.release()
                yield list(zip(batch, outcomes))
                submit_next()
                publish(len(in_flight))
        finally:
            left = [f for f, _ in in_flight.values() if not f.done()]
            if left:
                self.client.cancel(left)

    def close(self) -> None:
        if self.core_share is not None:
            self.core_share.remove()
        if self._own_client:
            self.client.close()
            if self._cluster is not None:
                self._cluster.close()
                self._cluster = None


@dataclass(frozen=True)
class RunSummary:
    """What one ``run_pending`` call did: outcomes written and batches run by this process."""

    n_done: int
    n_failed: int
    n_batches: int


class _LeaseKeeper:
    """Background thread renewing the leases of claimed, unfinished tasks every `period` s."""

    def __init__(self, store: CampaignStore, period: float):
        self._store = store
        self._period = period
        self._ids: set[int] = set()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="lease-keeper", daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    def hold(self, ids: Iterable[int]) -> None:
        with self._lock:
            self._ids.update(ids)

    def drop(self, ids: Iterable[int]) -> None:
        with self._lock:
            self._ids.difference_update(ids)

    @property
    def held(self) -> list[int]:
        with self._lock:
            return sorted(self._ids)

    def _loop(self):
        while not self._stop.wait(self._period):
            ids = self.held
            if ids:
                try:
                    self._store.renew(ids)
                except Exception:  # a busy DB now is retried next period; the lease is long
                    pass


def run_pending(store: CampaignStore, executor: Executor, stage: str | None = None, *,
                wait: bool = True, poll_seconds: float = 2.0, batch_key: str | None = None) -> RunSummary:
    """Run every pending task of ``stage`` (all stages if None; ``batch_key``: of that batch of
    ``stage`` only) and store each outcome.

    Claims one batch at a time (``executor.batch_size`` tasks of one condition,
    :meth:`CampaignStore.claim`) whenever the executor has a free worker (``run_stream``: the
    executor keeps ``parallelism`` batches in flight, so a worker that finishes a short batch
    takes the next at once instead of waiting for a long one elsewhere), writes each batch's
    outcomes in one transaction as soon as the batch finishes, and repeats until nothing is
    claimable. On an exception (including KeyboardInterrupt) the unfinished claims are
    released back to pending; after a SIGKILL they go stale and are claimed again by the next
    run. With ``wait=True`` it then waits (polling every ``poll_seconds``) for tasks other
    live processes are running, so on return every task of ``stage`` is done or failed.
    """
    if not isinstance(executor, Executor):
        raise out_of_range("executor", executor, "an Executor (InProcessExecutor, DaskExecutor)",
                           "run_pending")
    if stage is not None:
        store.check_stage(stage, "run_pending")
    n_done = n_failed = n_batches = 0
    with _LeaseKeeper(store, store.renew_period) as keeper:
        while True:
            claimed = []

            def feed():  # one claim at a time, drawn as a worker frees up
                while True:
                    tasks = store.claim(executor.batch_size, stage=stage, batch_size=executor.batch_size,
                                        affinity=executor.affinity, batch_key=batch_key)
                    if not tasks:
                        return
                    keeper.hold(t.task_id for t in tasks)
                    claimed.append(len(tasks))
                    # a claim tops up a condition's short last batch with another condition's
                    # tasks; an ensemble holds one condition, so the claim is cut where it changes
                    yield from make_batches(tasks, executor.batch_size)

            try:
                for finished in executor.run_stream(feed()):
                    store.record(finished)
                    keeper.drop(t.task_id for t, _ in finished)
                    n_batches += 1
                    n_done += sum(o.ok for _, o in finished)
                    n_failed += sum(not o.ok for _, o in finished)
            except BaseException:
                store.release(keeper.held)
                raise
            if not claimed:
                if not wait or store.counts(stage, batch_key=batch_key).get("running", 0) == 0:
                    break
                time.sleep(poll_seconds)  # others are still running tasks; theirs may go stale
                continue
            leftover = keeper.held
            if leftover:  # a broken executor skipped tasks: give them back and say so
                store.release(leftover)
                raise RuntimeError(
                    f"{type(executor).__name__}.run yielded no outcome for task ids {leftover}; "
                    "they were released back to pending")
    return RunSummary(n_done, n_failed, n_batches)
