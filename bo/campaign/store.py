"""Campaign store: every DEM evaluation, batch proposal and stage output of a calibration.

Contract
--------
``CampaignStore(path, config_hash, code_version=None)`` opens (or creates) one SQLite file in
WAL mode. It is safe for several processes at once on one machine (WAL needs shared memory,
so the file must be on a local disk, not NFS/Lustre shared between hosts): every write is one
``BEGIN IMMEDIATE`` transaction, waits up to ``busy_timeout`` seconds for the write lock, and
a connection is opened per operation (so a store object may be used from threads and
survives ``fork``). A SIGKILL at any point leaves the file consistent; it loses at most the
evaluations in flight.

Evaluations (table ``evaluations``), one row per ``(stage, batch key, point, seed,
condition)``, with:

* ``stage``: ``"screening"``, ``"initial"``, ``"round-<n>"``, ``"verification"``,
  ``"validation"``, or one of the constructor's ``extra_stages``; anything else is refused, so
  a typo cannot silently start a new batch;
* ``batch_key``, ``point_index``, ``params`` (canonical JSON: sorted keys, floats as ``repr``,
  so they read back bit-identical), ``seed``, ``condition``;
* ``config_hash`` and ``code_version`` of the process that *finished* the evaluation (at
  creation: of the proposer). The default code version is the repo's git commit, with
  ``+dirty`` when tracked files differ from it, else the installed package version;
* ``status``: ``pending`` -> ``running`` -> ``done`` | ``failed``;
* ``kpis`` (JSON; non-finite KPI values are stored as ``null`` and read back as NaN),
  ``error`` (message), ``wall_time`` [s];
* ``claimed_by`` (``"host:pid"``), ``claimed_at``, ``attempts``, ``created_at``,
  ``finished_at`` (Unix seconds).

Batches: ``batch(stage, key, make_points, seeds=..., conditions=...)`` (seeds and conditions
are required keywords: the tasks of a point are its seeds x conditions) returns the stored
points of that batch if it exists; otherwise it calls ``make_points()`` once, stores the
points (and one pending task per point x seed x condition, condition-major) in one
transaction and returns them. A resumed campaign therefore re-uses the proposals made before
a kill. If two processes race to create the same batch, the first commit wins and both
return its points. A stored batch grows: asked for with more seeds or conditions (a superset of the
stored ones), it stores the new lists (the stored entries first, in their order, then the new
ones) and one pending task for each new point x seed x condition, which takes a run already done
in its stage where there is one (see "Shared runs"); its stored runs stay as they are. Asking for
fewer seeds or conditions than are stored is an error: a batch never loses runs.

Shared runs: within a stage, an evaluation is the same run wherever it is asked for when its
parameters (canonical JSON), seed, condition and config hash are equal (not across stages: the
stages of a discovery evaluate different models, extended by different mechanisms, under one
config). A new batch's task whose run is already ``done`` in a batch of its stage is stored
``done`` at once with that run's KPIs (``claimed_by = "reused:<task id>"``, no wall time: it
cost nothing), and when a task finishes, the pending tasks of the same run in its stage are
completed with it. So a seed list that grows, or a design run again for another twin, costs no
DEM time (a stage must therefore always evaluate one model); ``EvaluationRecord.reused_from``
names the run a row took its result from,
and ``counts(..., computed_only=True)`` counts only evaluations that ran. ``adopt`` completes a
batch's tasks with runs of another store (the calibration's verification runs of the set a discovery
starts from): ``claimed_by = "imported:<store>#<task id>"``, no wall time, not counted as computed.

Claiming: ``claim(limit, stage)`` marks up to ``limit`` claimable tasks ``running`` under a
lease (``claimed_by``, ``claimed_at``) inside one IMMEDIATE transaction, so two processes
never claim the same task. Claimable = ``pending``, or ``running`` with a stale lease: the
owner is on this host and its process is gone (or a zombie), or the lease is older than
``lease_seconds`` (owners renew their leases every ``lease_seconds / 3`` while they work, see
``bo.campaign.executor.run_pending``; clocks of hosts sharing a store must agree to well within
``lease_seconds``). One claim holds tasks of a single condition (that of the oldest claimable
task), so it cuts into full single-condition ensemble batches. ``record`` writes finished
outcomes (one transaction per call) and never overwrites a ``done`` or ``failed`` row, so a
task that was re-claimed after a stale lease is stored once. ``release`` gives unfinished
claims back, ``reset_failed`` re-queues failures.

Artifacts: ``put_artifact(name, value)`` stores a JSON-able stage output (GA result, fitted
choices; strict JSON, no NaN/inf) and ``get_artifact(name)`` returns it, so finished stages are
not redone.

Queries return plain data: ``records(...)`` a list of frozen ``EvaluationRecord``,
``arrays(...)`` a ``ResultArrays`` with ``X [n, d]``, ``kpis [n, n_kpi]`` (NaN where missing),
``seeds [n]`` and the names of the columns.

The store remembers the config hash it was created with; opening it with another hash raises
``ConfigError`` naming both hashes and the path unless ``allow_config_mismatch=True``, or the
store's hash is one of ``also_accepts`` (the same model hashed by an earlier rule), which the
store then keeps for its rows.
"""
from __future__ import annotations

import functools
import json
import math
import os
import re
import socket
import sqlite3
import subprocess
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path

import numpy as np

from bo.campaign.executor import EvalOutcome, EvalTask, canonical_params
from torchdem.errors import ConfigError, out_of_range

__all__ = [
    "STAGES",
    "STATUSES",
    "CampaignStore",
    "EvaluationRecord",
    "ResultArrays",
    "default_code_version",
]

STAGES = ("screening", "initial", "verification", "validation")
"""Stage names always accepted; ``round-<n>`` (n >= 1) is accepted too."""
_ROUND = re.compile(r"round-[1-9][0-9]*")
STATUSES = ("pending", "running", "done", "failed")
#: ``claimed_by`` prefix of a row completed with another row's result (see "Shared runs").
REUSED = "reused:"
#: ``claimed_by`` prefix of a row completed with a run of another store (:meth:`CampaignStore.adopt`).
IMPORTED = "imported:"
#: The done original of the same run as ``evaluations`` (correlated sub-query, see "Shared runs").
_SAME_RUN_DONE = ("FROM evaluations d WHERE d.status = 'done' AND d.stage = evaluations.stage "
                  "AND d.params = evaluations.params "
                  "AND d.seed = evaluations.seed AND d.condition = evaluations.condition "
                  "AND d.config_hash = evaluations.config_hash AND d.claimed_by NOT LIKE 'reused:%'")
SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS batches (
    stage TEXT NOT NULL,
    batch_key TEXT NOT NULL,
    points TEXT NOT NULL,
    seeds TEXT NOT NULL,
    conditions TEXT NOT NULL,
    config_hash TEXT NOT NULL,
    code_version TEXT NOT NULL,
    created_at REAL NOT NULL,
    PRIMARY KEY (stage, batch_key)
);
CREATE TABLE IF NOT EXISTS evaluations (
    task_id INTEGER PRIMARY KEY AUTOINCREMENT,
    stage TEXT NOT NULL,
    batch_key TEXT NOT NULL,
    point_index INTEGER NOT NULL,
    params TEXT NOT NULL,
    seed INTEGER NOT NULL,
    condition TEXT NOT NULL,
    config_hash TEXT NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('pending', 'running', 'done', 'failed')),
    kpis TEXT,
    error TEXT,
    wall_time REAL,
    code_version TEXT NOT NULL,
    created_at REAL NOT NULL,
    claimed_by TEXT,
    claimed_at REAL,
    finished_at REAL,
    attempts INTEGER NOT NULL DEFAULT 0,
    UNIQUE (stage, batch_key, point_index, seed, condition),
    FOREIGN KEY (stage, batch_key) REFERENCES batches (stage, batch_key)
);
CREATE INDEX IF NOT EXISTS evaluations_by_status ON evaluations (status, stage);
CREATE INDEX IF NOT EXISTS evaluations_by_run ON evaluations (condition, seed, params);
CREATE TABLE IF NOT EXISTS artifacts (
    name TEXT PRIMARY KEY,
    value TEXT NOT NULL,
    config_hash TEXT NOT NULL,
    code_version TEXT NOT NULL,
    updated_at REAL NOT NULL
);
"""

_MISSING = object()


#: The meta key of a copied store: JSON ``{"source", "copied_at", "last_task_id"}``; the rows up to
#: ``last_task_id`` were made in ``source`` (``bo.campaign.progress`` counts their cost there).
COPIED_FROM = "copied_from"


def open_read_only(path: Path, source: str = "store_progress") -> sqlite3.Connection:
    """A read-only connection to a campaign store (it never writes, and waits on no writer). A file
    that is missing, not SQLite, or without the store's tables raises ``ConfigError`` naming it and
    ``source`` (the SQLite error chained)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"campaign store {str(path)!r} does not exist ({source})")
    try:
        conn = sqlite3.connect(path.resolve().as_uri() + "?mode=ro", uri=True)
        conn.execute("SELECT 1 FROM evaluations LIMIT 1")
    except sqlite3.DatabaseError as exc:
        raise ConfigError(f"{path}: not a campaign store ({exc}) ({source})") from exc
    return conn


def copy_store(source: Path, target: Path) -> None:
    """Copy the campaign store file ``source`` to ``target`` (replaced if it exists), consistent even
    while another process writes the source (SQLite's backup API; the source is opened read-only,
    :func:`open_read_only`, so a file that is not a campaign store raises ``ConfigError`` before any
    target is made), and note in the copy's meta (``COPIED_FROM``) which rows came with it."""
    read = open_read_only(source, "copy_store")
    target.parent.mkdir(parents=True, exist_ok=True)
    write = sqlite3.connect(target)
    try:
        read.backup(write)
        with write:
            (last,) = write.execute("SELECT COALESCE(MAX(task_id), 0) FROM evaluations").fetchone()
            note = {"source": str(source), "copied_at": time.time(), "last_task_id": int(last)}
            write.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (COPIED_FROM, json.dumps(note)))
    finally:
        write.close()
        read.close()


@functools.lru_cache(maxsize=1)
def default_code_version() -> str:
    """The git commit of the repo holding this package (``+dirty`` if tracked files changed),
    else the installed torchdem version, else ``"unknown"``."""
    repo = Path(__file__).resolve().parent
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}  # never touch the index
    try:
        commit = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], env=env,
                                capture_output=True, text=True, timeout=10, check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(repo), "status", "--porcelain",
                                 "--untracked-files=no"], env=env, capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip()
        if commit:
            return commit + ("+dirty" if status else "")
    except (OSError, subprocess.SubprocessError):
        pass
    try:
        from importlib.metadata import version
        return "torchdem " + version("torchdem")
    except Exception:
        return "unknown"


def affinity_distance(a: tuple, b: tuple) -> float:
    """Summed relative difference of two affinity keys' values (inf if their names differ)."""
    if [n for n, _ in a] != [n for n, _ in b]:
        return math.inf
    return sum(abs(x - y) / max(abs(x), abs(y)) for (_, x), (_, y) in zip(a, b) if x != y)


def _by_affinity(rows: list, batch_size: int, affinity: Callable[[Mapping[str, float]], tuple], needed: int) -> list:
    """The first ``needed`` (or more, to a whole batch) of ``rows`` (task order; params JSON in
    column 1) reordered batch by batch: each batch the oldest row left, then rows of equal
    affinity in task order, then the nearest ones."""
    buckets: dict[tuple, list] = {}
    for row in rows:
        buckets.setdefault(tuple(affinity(json.loads(row[1]))), []).append(row)
    if len(buckets) <= 1:
        return rows
    position = {row[0]: k for k, row in enumerate(rows)}
    out: list = []
    while buckets and len(out) < needed:
        first = min(buckets, key=lambda key: position[buckets[key][0][0]])
        batch: list = []
        for key in sorted(buckets, key=lambda key: (affinity_distance(first, key), position[buckets[key][0][0]])):
            take = buckets[key][:batch_size - len(batch)]
            batch += take
            buckets[key] = buckets[key][len(take):]
            if not buckets[key]:
                del buckets[key]
            if len(batch) == batch_size:
                break
        out += batch
    return out


def _owner() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def _owner_is_gone(owner: str | None) -> bool:
    """True when ``owner`` ("host:pid") is a process on this host that no longer runs."""
    if not owner or os.name != "posix":
        return False
    host, _, pid_text = owner.rpartition(":")
    if host != socket.gethostname() or not pid_text.isdigit():
        return False  # another host: only the lease timeout can tell
    pid = int(pid_text)
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # alive, owned by another user
    try:  # a killed child its parent has not reaped yet still answers kill(pid, 0)
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except (OSError, IndexError):
        return False


def _dumps(value) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _kpis_json(kpis: Mapping[str, float]) -> str:
    return _dumps({k: (v if math.isfinite(v) else None) for k, v in kpis.items()})


def _kpis_from_json(text: str | None) -> dict[str, float] | None:
    if text is None:
        return None
    return {k: (math.nan if v is None else float(v)) for k, v in json.loads(text).items()}


#: The ``evaluations`` columns of an :class:`EvaluationRecord`, in its fields' order.
RECORD_COLUMNS = ("task_id, stage, batch_key, point_index, params, seed, condition, config_hash, status, kpis, "
                  "error, wall_time, code_version, created_at, claimed_by, claimed_at, finished_at, attempts")


def record_from_row(row: Sequence) -> "EvaluationRecord":
    """The record of a row selected as :data:`RECORD_COLUMNS` (parameters and KPIs parsed, a KPI
    stored as null NaN)."""
    return EvaluationRecord(row[0], row[1], row[2], row[3], json.loads(row[4]), row[5], row[6], row[7], row[8],
                            _kpis_from_json(row[9]), *row[10:])


def reused_from(claimed_by: str | None) -> int | None:
    """Task id of the run whose result a row with this ``claimed_by`` took (see "Shared runs"), else None."""
    if claimed_by and claimed_by.startswith(REUSED):
        return int(claimed_by[len(REUSED):])
    return None


@dataclass(frozen=True)
class EvaluationRecord:
    """One row of the ``evaluations`` table (times in Unix seconds, wall time in seconds)."""

    task_id: int
    stage: str
    batch_key: str
    point_index: int
    params: dict[str, float]
    seed: int
    condition: str
    config_hash: str
    status: str
    kpis: dict[str, float] | None
    error: str | None
    wall_time: float | None
    code_version: str
    created_at: float
    claimed_by: str | None
    claimed_at: float | None
    finished_at: float | None
    attempts: int

    def __hash__(self) -> int:
        return hash(self.task_id)

    @property
    def task(self) -> EvalTask:
        return EvalTask(self.params, self.seed, self.condition, self.task_id)

    @property
    def reused_from(self) -> int | None:
        """Task id of the run whose result this row took (see "Shared runs"), else None."""
        return reused_from(self.claimed_by)


@dataclass(frozen=True)
class ResultArrays:
    """Finished evaluations as arrays, row ``i`` of every array is one evaluation.

    Attributes:
        X: [n, d] float64 parameters, columns ``param_names`` (NaN where a row lacks one).
        kpis: [n, n_kpi] float64 KPIs, columns ``kpi_names`` (NaN where missing / non-finite).
        seeds: [n] int64.
        conditions: [n] str.
        stages: [n] str.
        task_ids: [n] int64 store row ids.
        param_names, kpi_names: column names, sorted unless the caller chose them.
    """

    X: np.ndarray
    kpis: np.ndarray
    seeds: np.ndarray
    conditions: np.ndarray
    stages: np.ndarray
    task_ids: np.ndarray
    param_names: tuple[str, ...]
    kpi_names: tuple[str, ...]


def _check_name(name, what: str, source: str) -> str:
    if not isinstance(name, str) or not name:
        raise out_of_range(what, name, "a non-empty str", source)
    return name


class CampaignStore:
    """SQLite store of a calibration campaign; see the module docstring for the contract.

    Args:
        path: the database file (created with its parent directory if missing).
        config_hash: hash of the campaign config; must match the one the store was created with.
        code_version: recorded with every write; default ``default_code_version()``.
        allow_config_mismatch: open a store created with another config hash anyway.
        also_accepts: other hashes of the same model (the hashes of an earlier hashing rule,
            ``bo.cli.common.store_hashes``): a store created with one of them opens, and its runs
            keep that hash (``self.config_hash`` becomes the store's).
        lease_seconds: age after which a claim of a live-looking owner counts as stale.
        busy_timeout: seconds to wait for another process's write transaction.
        extra_stages: stage names accepted besides ``STAGES`` and ``round-<n>``.
    """

    def __init__(self, path: str | os.PathLike, config_hash: str, code_version: str | None = None,
                 *, allow_config_mismatch: bool = False, also_accepts: Iterable[str] = (),
                 lease_seconds: float = 900.0, busy_timeout: float = 60.0, extra_stages: Iterable[str] = ()):
        source = "CampaignStore"
        if not isinstance(path, (str, os.PathLike)) or str(path) in ("", ":memory:"):
            raise out_of_range("path", path, "a database file path (not ':memory:')", source)
        self.path = Path(path)
        self.config_hash = _check_name(config_hash, "config_hash", source)
        #: every hash of this store's model: the one given first, then ``also_accepts``
        self.model_hashes = tuple(dict.fromkeys([self.config_hash, *(_check_name(h, "also_accepts entry", source)
                                                                      for h in also_accepts)]))
        self.code_version = (default_code_version() if code_version is None
                             else _check_name(code_version, "code_version", source))
        for name, value in (("lease_seconds", lease_seconds), ("busy_timeout", busy_timeout)):
            if isinstance(value, bool) or not isinstance(value, Real) or not value > 0 \
                    or not math.isfinite(value):
                raise out_of_range(name, value, "a finite number of seconds > 0", source)
        self.lease_seconds = float(lease_seconds)
        self.busy_timeout = float(busy_timeout)
        self.extra_stages = tuple(_check_name(s, "extra_stages entry", source) for s in extra_stages)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # a path under a file, a read-only or missing mount
            raise ConfigError(f"{self.path}: cannot make the store's folder {self.path.parent} "
                              f"({exc.strerror or exc})") from exc
        self._init_db()
        self.stored_config_hash = self._meta("config_hash")
        if self.stored_config_hash in self.model_hashes:
            self.config_hash = self.stored_config_hash
        if self.stored_config_hash != self.config_hash and not allow_config_mismatch:
            raise ConfigError(
                f"{self.path}: campaign store was created with config hash "
                f"{self.stored_config_hash!r} but this run has config hash {self.config_hash!r}; "
                "use a new store path for the new config, or pass allow_config_mismatch=True to "
                "continue this campaign anyway")

    # -- connections -------------------------------------------------------------------------

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, timeout=self.busy_timeout, isolation_level=None)
        conn.execute(f"PRAGMA busy_timeout = {int(self.busy_timeout * 1000)}")
        conn.execute("PRAGMA synchronous = FULL")
        conn.execute("PRAGMA foreign_keys = ON")
        return conn

    @contextmanager
    def _write(self):
        """One IMMEDIATE transaction: the write lock is taken at BEGIN, so reads inside it
        see the state no other writer can change until COMMIT."""
        conn = self._connect()
        try:
            conn.execute("BEGIN IMMEDIATE")
            yield conn
            conn.execute("COMMIT")
        except BaseException:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            raise
        finally:
            conn.close()

    def _init_db(self) -> None:
        try:
            conn = self._connect()
        except sqlite3.DatabaseError as exc:
            raise ConfigError(f"{self.path}: not a usable SQLite database ({exc})") from exc
        try:
            deadline = time.monotonic() + self.busy_timeout
            while True:  # switching to WAL needs a moment without other writers
                try:
                    mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
                    break
                except sqlite3.OperationalError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.05)
            if mode.lower() != "wal":
                raise ConfigError(f"{self.path}: SQLite refused WAL journal mode (got {mode!r}); "
                                  "put the campaign store on a local file system")
        except sqlite3.DatabaseError as exc:
            raise ConfigError(f"{self.path}: not a usable SQLite database ({exc})") from exc
        finally:
            conn.close()
        with self._write() as conn:
            for statement in _SCHEMA.split(";"):  # not executescript: it would COMMIT early
                if statement.strip():
                    conn.execute(statement)
            now = time.time()
            for key, value in (("schema_version", str(SCHEMA_VERSION)),
                               ("config_hash", self.config_hash),
                               ("created_at", repr(now)),
                               ("created_by_code_version", self.code_version)):
                conn.execute("INSERT OR IGNORE INTO meta (key, value) VALUES (?, ?)", (key, value))
            stored = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0]
        if stored != str(SCHEMA_VERSION):
            raise ConfigError(f"{self.path}: campaign store schema version {stored} is not the "
                              f"supported version {SCHEMA_VERSION}")

    def _meta(self, key: str) -> str | None:
        conn = self._connect()
        try:
            row = conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        finally:
            conn.close()
        return None if row is None else row[0]

    # -- validation --------------------------------------------------------------------------

    @property
    def renew_period(self) -> float:
        """How often a worker renews its leases (a third of ``lease_seconds``)."""
        return self.lease_seconds / 3.0

    def check_stage(self, stage, source: str = "CampaignStore") -> str:
        """Return ``stage`` if it is an accepted stage name, else raise ``ConfigError``."""
        if isinstance(stage, str) and (stage in STAGES or stage in self.extra_stages
                                       or _ROUND.fullmatch(stage)):
            return stage
        allowed = ", ".join(repr(s) for s in STAGES + self.extra_stages)
        raise out_of_range("stage", stage, f"one of {allowed} or 'round-<n>' with n >= 1 "
                           "(more via CampaignStore(extra_stages=...))", source)

    # -- batches -----------------------------------------------------------------------------

    def batch(self, stage: str, key: str, make_points: Callable[[], Sequence[Mapping[str, float]]],
              *, seeds: Sequence[int], conditions: Sequence[str], share: bool = True) -> list[dict[str, float]]:
        """Points of batch ``(stage, key)``: the stored ones, else ``make_points()`` stored.

        New points are stored with one pending task per point x seed x condition. Every point
        must have the same parameter names and finite values. ``share=False`` runs every task
        afresh even where the same run is done elsewhere (a verification rerun on a new
        machine); its results are still shared with batches created later.
        """
        source = f"CampaignStore.batch({stage!r}, {key!r})"
        self.check_stage(stage, source)
        _check_name(key, "batch key", source)
        seeds = self._check_seeds(seeds, source)
        conditions = self._check_conditions(conditions, source)
        stored = self._stored_batch(stage, key)
        if stored is None:
            points = self._check_points(make_points(), f"{source}: make_points()")
            with self._write() as conn:
                stored = self._stored_batch(stage, key, conn)  # another process may have won
                if stored is None:
                    self._insert_batch(conn, stage, key, points, seeds, conditions, share)
                    return [dict(p) for p in points]
        points, stored_seeds, stored_conditions = stored
        if not (set(stored_seeds) <= set(seeds) and set(stored_conditions) <= set(conditions)):
            raise ConfigError(
                f"{self.path}: {source} is stored with seeds={stored_seeds} and "
                f"conditions={stored_conditions}, but seeds={seeds} and conditions={conditions} "
                "were asked for; a stored batch can grow by seeds or conditions but never lose any: "
                "ask for at least the stored ones, or use a new batch key for a different design")
        if set(seeds) - set(stored_seeds) or set(conditions) - set(stored_conditions):
            seeds, conditions = self._grow_batch(stage, key, seeds, conditions)
        else:
            seeds, conditions = stored_seeds, stored_conditions
        self._add_missing_tasks(stage, key, points, seeds, conditions, share)
        return points

    def _grow_batch(self, stage: str, key: str, seeds: list[int], conditions: list[str]) -> tuple[list[int], list[str]]:
        """The stored seed and condition lists of batch ``(stage, key)`` extended by the new entries of
        ``seeds`` and ``conditions`` (the stored ones first, in their order), stored and returned; the
        runs they add are :meth:`_add_missing_tasks`'."""
        with self._write() as conn:
            _, stored_seeds, stored_conditions = self._stored_batch(stage, key, conn)
            seeds = stored_seeds + [s for s in seeds if s not in stored_seeds]
            conditions = stored_conditions + [c for c in conditions if c not in stored_conditions]
            conn.execute("UPDATE batches SET seeds = ?, conditions = ? WHERE stage = ? AND batch_key = ?",
                         (_dumps(seeds), _dumps(conditions), stage, key))
        return seeds, conditions

    def near_batch(self, stage: str, prefix: str, points: Sequence[Mapping[str, float]], *, seeds: Sequence[int],
                   conditions: Sequence[str], tolerance: Mapping[str, float]
                   ) -> tuple[str, list[dict[str, float]]] | None:
        """``(key, stored points)`` of the batch of ``stage`` whose key starts with ``prefix``, stored
        with these ``seeds`` and ``conditions``, whose points are ``points`` in order within
        ``tolerance`` (absolute, per parameter; a parameter not named there must be equal); of several,
        the closest (largest difference in units of the tolerance), then the oldest; None if there is
        none.

        For points a computation chose (a fit's optimum): resumed on another machine, its floating
        point (another BLAS, another vector width) moves them in the last digits, and a key hashed
        from the exact values would run the same experiment again. The caller says how close is
        the same experiment."""
        source = f"CampaignStore.near_batch({stage!r}, {prefix!r})"
        self.check_stage(stage, source)
        want = self._check_points(points, source)
        seeds, conditions = self._check_seeds(seeds, source), self._check_conditions(conditions, source)
        names = sorted(want[0]) if want else []
        for name, tol in tolerance.items():
            if not (isinstance(tol, Real) and math.isfinite(tol) and tol >= 0):
                raise out_of_range(f"tolerance[{name!r}]", tol, "a finite float >= 0", source)
        atol = np.array([float(tolerance.get(n, 0.0)) for n in names])
        x = np.array([[p[n] for n in names] for p in want])
        conn = self._connect()
        try:
            rows = conn.execute("SELECT batch_key, points, seeds, conditions FROM batches WHERE stage = ? "
                                "AND substr(batch_key, 1, ?) = ? ORDER BY created_at, rowid",
                                (stage, len(prefix), prefix)).fetchall()
        finally:
            conn.close()
        best, found = math.inf, None
        for key, stored_points, stored_seeds, stored_conditions in rows:
            if json.loads(stored_seeds) != seeds or json.loads(stored_conditions) != conditions:
                continue
            stored = json.loads(stored_points)
            if len(stored) != len(want) or any(sorted(p) != names for p in stored):
                continue
            gap = np.abs(np.array([[p[n] for n in names] for p in stored]) - x)
            if np.all(gap <= atol):  # a difference in units of the tolerance (0 where it is 0 and equal)
                distance = float(np.max(np.where(atol > 0, gap / np.where(atol > 0, atol, 1.0), 0.0), initial=0.0))
                if distance < best:
                    best, found = distance, (key, [dict(p) for p in stored])
        return found

    def _add_missing_tasks(self, stage, key, points, seeds, conditions, share: bool = True) -> None:
        """Pending tasks for the runs the batch lacks: those :meth:`withdraw_batch` took away, and those
        of the seeds or conditions it grew by (:meth:`_grow_batch`); each takes a run done elsewhere in
        the stage unless ``share`` is false."""
        conn = self._connect()
        try:
            have = conn.execute("SELECT COUNT(*) FROM evaluations WHERE stage = ? AND batch_key = ?",
                                (stage, key)).fetchone()[0]
        finally:
            conn.close()
        if have == len(points) * len(seeds) * len(conditions):
            return
        with self._write() as conn:
            present = {(i, seed, condition) for i, seed, condition in conn.execute(
                "SELECT point_index, seed, condition FROM evaluations WHERE stage = ? AND batch_key = ?", (stage, key))}
            now = time.time()
            self._insert_tasks(conn, stage, key, points, seeds, conditions, now, skip=present)
            if share:
                self._take_shared(conn, stage, key, now)

    def _stored_batch(self, stage: str, key: str, conn: sqlite3.Connection | None = None):
        own = conn is None
        conn = self._connect() if own else conn
        try:
            row = conn.execute("SELECT points, seeds, conditions FROM batches "
                               "WHERE stage = ? AND batch_key = ?", (stage, key)).fetchone()
        finally:
            if own:
                conn.close()
        if row is None:
            return None
        return json.loads(row[0]), json.loads(row[1]), json.loads(row[2])

    def _insert_batch(self, conn, stage, key, points, seeds, conditions, share: bool = True) -> None:
        now = time.time()
        conn.execute("INSERT INTO batches (stage, batch_key, points, seeds, conditions, config_hash, "
                     "code_version, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                     (stage, key, json.dumps(points, separators=(",", ":"), allow_nan=False),
                      _dumps(seeds), _dumps(conditions), self.config_hash, self.code_version, now))
        self._insert_tasks(conn, stage, key, points, seeds, conditions, now)
        if share:
            self._take_shared(conn, stage, key, now)

    def _insert_tasks(self, conn, stage, key, points, seeds, conditions, now: float, skip=frozenset()) -> None:
        """One pending task per point x seed x condition of the batch, but those in ``skip``
        (``(point_index, seed, condition)``)."""
        conn.executemany(
            "INSERT INTO evaluations (stage, batch_key, point_index, params, seed, condition, "
            "config_hash, status, code_version, created_at) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, 'pending', ?, ?)",
            [(stage, key, i, _dumps(point), seed, condition, self.config_hash, self.code_version, now)
             for condition in conditions for i, point in enumerate(points) for seed in seeds
             if (i, seed, condition) not in skip])

    @staticmethod
    def _take_shared(conn, stage: str, key: str, now: float) -> None:
        """The batch's pending runs that are done elsewhere take that result (see "Shared runs")."""
        conn.execute(
            "UPDATE evaluations SET (status, kpis, error, wall_time, code_version, claimed_by, finished_at) = "
            f"(SELECT 'done', d.kpis, NULL, NULL, d.code_version, '{REUSED}' || d.task_id, ? {_SAME_RUN_DONE} "
            "ORDER BY d.task_id LIMIT 1) "
            f"WHERE stage = ? AND batch_key = ? AND status = 'pending' AND EXISTS (SELECT 1 {_SAME_RUN_DONE})",
            (now, stage, key))

    @staticmethod
    def _check_seeds(seeds, source: str) -> list[int]:
        if isinstance(seeds, (str, bytes)) or not isinstance(seeds, Iterable):
            raise out_of_range("seeds", seeds, "a non-empty sequence of distinct ints", source)
        seeds = list(seeds)
        if not seeds or any(isinstance(s, bool) or not isinstance(s, Integral) for s in seeds) \
                or len(set(seeds)) != len(seeds):
            raise out_of_range("seeds", seeds, "a non-empty sequence of distinct ints", source)
        return [int(s) for s in seeds]

    @staticmethod
    def _check_conditions(conditions, source: str) -> list[str]:
        allowed = "a non-empty sequence of distinct non-empty str, e.g. ['50-50']"
        if isinstance(conditions, (str, bytes)) or not isinstance(conditions, Iterable):
            raise out_of_range("conditions", conditions, allowed, source)
        conditions = list(conditions)
        if not conditions or any(not isinstance(c, str) or not c for c in conditions) \
                or len(set(conditions)) != len(conditions):
            raise out_of_range("conditions", conditions, allowed, source)
        return conditions

    @staticmethod
    def _check_points(points, source: str) -> list[dict[str, float]]:
        if isinstance(points, (str, bytes, Mapping)) or not isinstance(points, Iterable):
            raise out_of_range("points", points, "a sequence of parameter dicts", source)
        out = [canonical_params(p, f"{source} point {i}") for i, p in enumerate(points)]
        for i, point in enumerate(out[1:], start=1):
            if point.keys() != out[0].keys():
                raise out_of_range(f"point {i} parameter names", sorted(point),
                                   f"the names of point 0, {sorted(out[0])}", source)
        return out

    # -- claiming and recording --------------------------------------------------------------

    def claim(self, limit: int, stage: str | None = None, batch_size: int = 1,
              affinity: Callable[[Mapping[str, float]], tuple] | None = None,
              batch_key: str | None = None) -> list[EvalTask]:
        """Lease up to ``limit`` claimable tasks to this process, grouped by condition: the
        claimable tasks of the condition of the oldest one first, then those of the condition of
        the oldest remaining one, and so on (task order kept within a condition). A later
        condition contributes whole batches of ``batch_size`` (or all its tasks, if they fit), so
        every claim splits into single-condition batches no smaller than a condition's last one,
        and when one condition has fewer tasks than the executor's workers can take, the other
        conditions' tasks keep them busy.

        ``affinity(params)`` (optional): a tuple of ``(name, value)`` pairs that should agree
        within a batch (``torchdem.model.mixture_parameters``: tasks of different particle shapes
        in one ensemble all run at the smallest one's time step). Each batch then starts with the
        oldest task left and is filled with the tasks of equal affinity, in task order, then of
        the nearest (summed relative difference of the values); the tasks come back batch by
        batch, so ``make_batches`` cuts them where the claim did.

        ``batch_key`` (optional): claim only the tasks of that batch of ``stage``. A stage that
        holds one design (the surrogate's initial design, each round) claims so, and a design the
        campaign no longer asks for (the screening's selection changed) is never run; it is run
        again if the campaign comes back to it."""
        if isinstance(limit, bool) or not isinstance(limit, Integral) or limit < 1:
            raise out_of_range("limit", limit, "an int >= 1", "CampaignStore.claim")
        if isinstance(batch_size, bool) or not isinstance(batch_size, Integral) or batch_size < 1:
            raise out_of_range("batch_size", batch_size, "an int >= 1", "CampaignStore.claim")
        where_stage, args = ("", []) if stage is None else (" AND stage = ?", [self.check_stage(stage)])
        if batch_key is not None:
            if stage is None:
                raise out_of_range("batch_key", batch_key, "a key together with its stage", "CampaignStore.claim")
            where_stage += " AND batch_key = ?"
            args.append(_check_name(batch_key, "batch key", "CampaignStore.claim"))
        owner, now = _owner(), time.time()
        with self._write() as conn:
            owners = [row[0] for row in conn.execute(
                "SELECT DISTINCT claimed_by FROM evaluations WHERE status = 'running'" + where_stage,
                args)]
            gone = [o for o in owners if _owner_is_gone(o)]
            marks = ", ".join("?" * len(gone))
            stale = f" OR claimed_by IN ({marks})" if gone else ""
            claimable = ("FROM evaluations WHERE (status = 'pending' OR (status = 'running' AND "
                         f"(claimed_at < ?{stale})))" + where_stage)
            claimable_args = [now - self.lease_seconds, *gone, *args]
            by_condition: dict[str, list] = {}
            for row in conn.execute("SELECT task_id, params, seed, condition " + claimable + " ORDER BY task_id",
                                    claimable_args):
                by_condition.setdefault(row[3], []).append(row)
            rows: list = []
            for group in by_condition.values():
                room = int(limit) - len(rows)
                if room <= 0:
                    break
                if affinity is not None:
                    group = _by_affinity(group, int(batch_size), affinity, room)
                take = len(group) if len(group) <= room else (room if not rows else room - room % batch_size)
                rows += group[:take]
            conn.executemany(
                "UPDATE evaluations SET status = 'running', claimed_by = ?, claimed_at = ?, "
                "attempts = attempts + 1 WHERE task_id = ?", [(owner, now, r[0]) for r in rows])
        return [EvalTask(json.loads(params), seed, condition, task_id)
                for task_id, params, seed, condition in rows]

    def lease(self, task_ids: Iterable[int], owner: str, until: float) -> list[EvalTask]:
        """Mark the pending tasks ``task_ids`` running under ``owner`` ("host:name") until the Unix
        time ``until``: for runs taken to a machine that cannot open this file (a GPU host without a
        shared disk, ``scripts/offload_runs.py``). No claim of this store takes them before
        ``until``; after it they are stale like any lease. Their outcomes come back through
        :meth:`record`. Returns the leased tasks; a task that is not pending is an error naming it."""
        ids = [int(i) for i in task_ids]
        if not ids:
            raise out_of_range("task_ids", ids, "at least one task id", "CampaignStore.lease")
        host, _, name = str(owner).rpartition(":")
        if not host or not name:
            raise out_of_range("owner", owner, "'host:name'", "CampaignStore.lease")
        if isinstance(until, bool) or not isinstance(until, Real) or not math.isfinite(until) \
                or until <= time.time():
            raise out_of_range("until", until, "a Unix time in the future", "CampaignStore.lease")
        with self._write() as conn:
            rows = {r[0]: r for r in conn.execute(
                f"SELECT task_id, params, seed, condition, status FROM evaluations WHERE task_id IN "
                f"({', '.join('?' * len(ids))})", ids)}
            for i in ids:
                if i not in rows or rows[i][4] != "pending":
                    raise out_of_range("task id", i, "a pending task of this store "
                                       f"(it is {rows[i][4] if i in rows else 'absent'})", "CampaignStore.lease")
            # claimed at until - lease_seconds: stale for claim() exactly at until
            conn.executemany("UPDATE evaluations SET status = 'running', claimed_by = ?, claimed_at = ?, "
                             "attempts = attempts + 1 WHERE task_id = ?",
                             [(str(owner), float(until) - self.lease_seconds, i) for i in ids])
        return [EvalTask(json.loads(rows[i][1]), rows[i][2], rows[i][3], i) for i in ids]

    def record(self, finished: Iterable[tuple[EvalTask, EvalOutcome]]) -> int:
        """Write outcomes in one transaction; returns how many rows were written.

        Rows already ``done``/``failed`` are left alone (a task re-claimed after a stale
        lease is stored once). Raises ``ConfigError`` if a task does not match its row.
        """
        finished = list(finished)
        owner, now, written = _owner(), time.time(), 0
        with self._write() as conn:
            for task, outcome in finished:
                if not isinstance(task, EvalTask) or not isinstance(outcome, EvalOutcome):
                    raise out_of_range("finished item", (task, outcome),
                                       "(EvalTask, EvalOutcome) pairs", "CampaignStore.record")
                row = conn.execute("SELECT params, seed, condition, status, stage FROM evaluations "
                                   "WHERE task_id = ?", (task.task_id,)).fetchone()
                if row is None or (json.loads(row[0]), row[1], row[2]) != \
                        (task.params, task.seed, task.condition):
                    raise ConfigError(f"{self.path}: task {task} does not match store row "
                                      f"{task.task_id} ({row and row[:3]}); tasks must come "
                                      "from claim() of this store")
                if row[3] in ("done", "failed"):
                    continue
                conn.execute(
                    "UPDATE evaluations SET status = ?, kpis = ?, error = ?, wall_time = ?, "
                    "code_version = ?, config_hash = ?, claimed_by = ?, finished_at = ? "
                    "WHERE task_id = ?",
                    ("done" if outcome.ok else "failed",
                     None if outcome.kpis is None else _kpis_json(outcome.kpis), outcome.error,
                     outcome.wall_time, self.code_version, self.config_hash, owner, now,
                     task.task_id))
                written += 1
                if outcome.ok:  # the same run asked for elsewhere, still pending, is done too
                    conn.execute(
                        "UPDATE evaluations SET status = 'done', kpis = ?, error = NULL, wall_time = NULL, "
                        "code_version = ?, claimed_by = ?, finished_at = ? WHERE status = 'pending' "
                        "AND stage = ? AND params = ? AND seed = ? AND condition = ? AND config_hash = ? AND task_id != ?",
                        (_kpis_json(outcome.kpis), self.code_version, f"{REUSED}{task.task_id}", now,
                         row[4], row[0], row[1], row[2], self.config_hash, task.task_id))
        return written

    def _update_own_running(self, sql: str, task_ids: Iterable[int], first: tuple = (),
                            owner: str | None = None) -> int:
        ids = [int(i) for i in task_ids]
        if not ids:
            return 0
        with self._write() as conn:
            cur = conn.executemany(
                sql + " WHERE task_id = ? AND status = 'running' AND claimed_by = ?",
                [(*first, i, _owner() if owner is None else str(owner)) for i in ids])
            return cur.rowcount

    def renew(self, task_ids: Iterable[int]) -> int:
        """Refresh this process's leases on ``task_ids``; returns how many were renewed."""
        return self._update_own_running("UPDATE evaluations SET claimed_at = ?", task_ids,
                                        (time.time(),))

    def release(self, task_ids: Iterable[int], owner: str | None = None) -> int:
        """Give this process's unfinished claims on ``task_ids`` back (status ``pending``); with
        ``owner``, that owner's (a :meth:`lease` whose runs did not come back)."""
        return self._update_own_running(
            "UPDATE evaluations SET status = 'pending', claimed_by = NULL, claimed_at = NULL",
            task_ids, owner=owner)

    def withdraw_batch(self, stage: str, key: str) -> int:
        """Withdraw the unfinished tasks of batch ``(stage, key)``: a design the campaign no longer
        asks for (the surrogate's initial design from before its parameters or bounds changed), so
        that its pending runs do not count as work left. Done and failed tasks stay (a later batch
        that asks for the same run takes its result); with none of them, the batch goes too.
        Refused while a task of it is running under a live lease. Asked for again, the batch gets
        its withdrawn tasks back (:meth:`batch`). Returns how many tasks were withdrawn."""
        source = f"CampaignStore.withdraw_batch({stage!r}, {key!r})"
        self.check_stage(stage, source)
        with self._write() as conn:
            if self._stored_batch(stage, key, conn) is None:
                raise ConfigError(f"{self.path}: {source}: no such batch; stored: "
                                  f"{[k for s, k in self.batch_keys(stage)]}")
            now = time.time()
            live = [task for task, claimed_by, claimed_at in conn.execute(
                "SELECT task_id, claimed_by, claimed_at FROM evaluations WHERE stage = ? AND batch_key = ? "
                "AND status = 'running'", (stage, key))
                if claimed_at is not None and claimed_at >= now - self.lease_seconds and not _owner_is_gone(claimed_by)]
            if live:
                raise ConfigError(f"{self.path}: {source}: task(s) {live} are running under a live lease; "
                                  "stop the campaign that runs them first")
            n = conn.execute("DELETE FROM evaluations WHERE stage = ? AND batch_key = ? "
                             "AND status IN ('pending', 'running')", (stage, key)).rowcount
            left = conn.execute("SELECT COUNT(*) FROM evaluations WHERE stage = ? AND batch_key = ?",
                                (stage, key)).fetchone()[0]
            if not left:
                conn.execute("DELETE FROM batches WHERE stage = ? AND batch_key = ?", (stage, key))
        return n

    def adopt(self, stage: str, key: str, runs: Sequence["EvaluationRecord"], source: str) -> int:
        """Complete pending tasks of batch ``(stage, key)`` with ``runs``, done evaluations of the same
        model in another store (``source``, its path; the caller vouches that they ran this batch's
        point): each run fills the task of its seed and condition (of point 0). Their KPIs are taken,
        ``claimed_by`` becomes ``imported:<source>#<task id>`` and the wall time is left empty (the
        run cost nothing here). Tasks already finished are left alone; returns how many were
        completed. Raises ``ConfigError`` for a run that is not done or has no task in the batch."""
        where = f"CampaignStore.adopt({stage!r}, {key!r})"
        self.check_stage(stage, where)
        stored = self._stored_batch(stage, key)
        if stored is None:
            raise ConfigError(f"{self.path}: {where}: no such batch; create it with batch() first")
        _, seeds, conditions = stored
        for run in runs:
            if run.status != "done" or run.kpis is None:
                raise out_of_range("run", f"task {run.task_id} of {source} ({run.status})", "done runs with KPIs",
                                   where)
            if run.seed not in seeds or run.condition not in conditions:
                raise out_of_range("run", f"task {run.task_id} of {source} (seed {run.seed}, {run.condition})",
                                   f"runs of the batch's seeds {seeds} and conditions {conditions}", where)
        now, written = time.time(), 0
        with self._write() as conn:
            for run in runs:
                written += conn.execute(
                    "UPDATE evaluations SET status = 'done', kpis = ?, error = NULL, wall_time = NULL, "
                    "code_version = ?, claimed_by = ?, finished_at = ? WHERE stage = ? AND batch_key = ? "
                    "AND point_index = 0 AND seed = ? AND condition = ? AND status = 'pending'",
                    (_kpis_json(run.kpis), run.code_version, f"{IMPORTED}{source}#{run.task_id}", now, stage, key,
                     run.seed, run.condition)).rowcount
        return written

    def reset_failed(self, stage: str | None = None) -> int:
        """Put failed tasks (of ``stage``, or all) back to pending; returns how many."""
        where_stage, args = ("", []) if stage is None else (" AND stage = ?", [self.check_stage(stage)])
        with self._write() as conn:
            return conn.execute(
                "UPDATE evaluations SET status = 'pending', error = NULL, kpis = NULL, "
                "wall_time = NULL, finished_at = NULL, claimed_by = NULL, claimed_at = NULL "
                "WHERE status = 'failed'" + where_stage, args).rowcount

    # -- queries -----------------------------------------------------------------------------

    def counts(self, stage: str | None = None, *, computed_only: bool = False,
               batch_key: str | None = None) -> dict[str, int]:
        """Number of tasks per status (all four statuses present); ``computed_only`` leaves out
        the rows that took another run's result (see "Shared runs") or were imported
        (:meth:`adopt`); ``batch_key`` counts one batch of ``stage``."""
        where_stage, args = ("", []) if stage is None else (" WHERE stage = ?", [self.check_stage(stage)])
        if batch_key is not None:
            if stage is None:
                raise out_of_range("batch_key", batch_key, "a key together with its stage", "CampaignStore.counts")
            where_stage += " AND batch_key = ?"
            args.append(batch_key)
        if computed_only:
            where_stage += ((" AND" if where_stage else " WHERE") + " COALESCE(claimed_by, '') NOT LIKE 'reused:%'"
                            " AND COALESCE(claimed_by, '') NOT LIKE 'imported:%'")
        out = dict.fromkeys(STATUSES, 0)
        conn = self._connect()
        try:
            for status, n in conn.execute(
                    "SELECT status, COUNT(*) FROM evaluations" + where_stage + " GROUP BY status", args):
                out[status] = n
        finally:
            conn.close()
        return out

    def records(self, stage: str | None = None, *, batch_key: str | None = None,
                condition: str | None = None, status: str | None = None) -> list[EvaluationRecord]:
        """Evaluation rows matching all given filters, in task id order."""
        clauses, args = [], []
        if stage is not None:
            clauses.append("stage = ?")
            args.append(self.check_stage(stage, "CampaignStore.records"))
        if status is not None:
            if status not in STATUSES:
                raise out_of_range("status", status, f"one of {STATUSES}", "CampaignStore.records")
            clauses.append("status = ?")
            args.append(status)
        for column, value in (("batch_key", batch_key), ("condition", condition)):
            if value is not None:
                clauses.append(f"{column} = ?")
                args.append(value)
        where = (" WHERE " + " AND ".join(clauses)) if clauses else ""
        conn = self._connect()
        try:
            rows = conn.execute(f"SELECT {RECORD_COLUMNS} FROM evaluations{where} ORDER BY task_id", args).fetchall()
        finally:
            conn.close()
        return [record_from_row(r) for r in rows]

    def arrays(self, stage: str | None = None, *, batch_key: str | None = None,
               condition: str | None = None, param_names: Sequence[str] | None = None,
               kpi_names: Sequence[str] | None = None) -> ResultArrays:
        """Done evaluations as arrays (see ``ResultArrays``); columns default to sorted names."""
        recs = self.records(stage, batch_key=batch_key, condition=condition, status="done")
        if param_names is None:
            param_names = sorted({n for r in recs for n in r.params})
        if kpi_names is None:
            kpi_names = sorted({n for r in recs for n in r.kpis})
        X = np.array([[r.params.get(n, math.nan) for n in param_names] for r in recs],
                     dtype=np.float64).reshape(len(recs), len(param_names))
        Y = np.array([[r.kpis.get(n, math.nan) for n in kpi_names] for r in recs],
                     dtype=np.float64).reshape(len(recs), len(kpi_names))
        return ResultArrays(
            X=X, kpis=Y,
            seeds=np.array([r.seed for r in recs], dtype=np.int64),
            conditions=np.array([r.condition for r in recs], dtype=str),
            stages=np.array([r.stage for r in recs], dtype=str),
            task_ids=np.array([r.task_id for r in recs], dtype=np.int64),
            param_names=tuple(param_names), kpi_names=tuple(kpi_names))

    def batch_keys(self, stage: str | None = None) -> list[tuple[str, str]]:
        """``(stage, key)`` of every stored batch, oldest first."""
        where_stage, args = ("", []) if stage is None else (" WHERE stage = ?", [self.check_stage(stage)])
        conn = self._connect()
        try:
            return [tuple(r) for r in conn.execute(
                "SELECT stage, batch_key FROM batches" + where_stage + " ORDER BY created_at, rowid",
                args)]
        finally:
            conn.close()

    # -- artifacts ---------------------------------------------------------------------------

    def put_artifact(self, name: str, value) -> None:
        """Store (or replace) a JSON-able stage output under ``name`` (strict JSON, no NaN)."""
        _check_name(name, "artifact name", "CampaignStore.put_artifact")
        try:
            text = _dumps(value)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{self.path}: artifact {name!r} is not strict JSON ({exc}); convert "
                              "arrays with .tolist() and non-finite floats to None") from exc
        with self._write() as conn:
            conn.execute("INSERT OR REPLACE INTO artifacts (name, value, config_hash, code_version, "
                         "updated_at) VALUES (?, ?, ?, ?, ?)",
                         (name, text, self.config_hash, self.code_version, time.time()))

    def get_artifact(self, name: str, default=_MISSING):
        """The artifact stored under ``name``; ``default`` if absent, or ``KeyError`` if no default."""
        conn = self._connect()
        try:
            row = conn.execute("SELECT value FROM artifacts WHERE name = ?", (name,)).fetchone()
        finally:
            conn.close()
        if row is not None:
            return json.loads(row[0])
        if default is not _MISSING:
            return default
        raise KeyError(f"{self.path}: no artifact {name!r}; stored: {self.artifact_names()}")

    def artifact_names(self) -> list[str]:
        conn = self._connect()
        try:
            return [r[0] for r in conn.execute("SELECT name FROM artifacts ORDER BY name")]
        finally:
            conn.close()

    def integrity_check(self) -> str:
        """``PRAGMA integrity_check`` of the file: ``"ok"`` when intact."""
        conn = self._connect()
        try:
            return "; ".join(r[0] for r in conn.execute("PRAGMA integrity_check"))
        finally:
            conn.close()

    def __repr__(self) -> str:
        return f"CampaignStore({str(self.path)!r}, config_hash={self.config_hash!r})"
