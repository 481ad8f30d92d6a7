"""What the campaign commands (screen, study, calibrate, discover) share: typed settings from the
plain config (executor, seeds, KPIs, screening design), the model of a one-condition config, the
store's config hash and path. Every bad value raises ``ConfigError`` naming its key.
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from omegaconf import DictConfig, OmegaConf

from torchdem.errors import ConfigError, out_of_range

#: Config blocks that decide DEM results; the store's config hash covers exactly these.
MODEL_KEYS = ("sim", "geometry", "mixture", "contact", "run", "condition", "extension")


# --------------------------------------------------------------------------------------------
# Typed settings from the plain config (shared with bo.cli.study)
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ExecutorSettings:
    """``conf/executor``: kind ``inprocess`` | ``dask``, ensemble size, dask options."""

    kind: str
    batch_size: int
    n_workers: int | None = None
    address: str | None = None
    max_in_flight: int | None = None
    share_cores: bool = True


def flag(value, key: str, where: str) -> bool:
    """A config value that must be true or false."""
    if not isinstance(value, bool):
        raise out_of_range(key, value, "true or false", where)
    return value


def _int(value, key: str, where: str, low: int, allowed: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise out_of_range(key, value, allowed, where)
    return int(value)


def _fraction(value, key: str, where: str, allowed: str, include_one: bool = False) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise out_of_range(key, value, allowed, where) from None
    if not (0.0 < x < 1.0 or (include_one and x == 1.0)):
        raise out_of_range(key, value, allowed, where)
    return x


def executor_settings_from(cfg: Mapping[str, Any], where: str = "executor") -> ExecutorSettings:
    kind = cfg.get("kind")
    if kind not in ("inprocess", "dask"):
        raise out_of_range("kind", kind, "'inprocess' or 'dask' (executor=inprocess|dask)", where)
    opt = lambda key: None if cfg.get(key) is None else _int(cfg[key], key, where, 1, "an int >= 1 or null")  # noqa: E731
    return ExecutorSettings(kind=kind, batch_size=_int(cfg.get("batch_size"), "batch_size", where, 1,
                                                       "an int >= 1 (ensemble members per DEM batch)"),
                            n_workers=opt("n_workers"), max_in_flight=opt("max_in_flight"),
                            address=None if cfg.get("address") is None else str(cfg["address"]),
                            share_cores=flag(cfg.get("share_cores", True), "share_cores", where))


def replicate_seeds(plain: Mapping[str, Any]) -> list[int]:
    """``seed, seed + 1, ..., seed + replicates - 1`` from the top-level keys."""
    replicates = _int(plain.get("replicates"), "replicates", "config", 1,
                      "an int >= 1 (replicates of the design, the paper uses 5)")
    seed = _int(plain.get("seed"), "seed", "config", 0, "an int >= 0 (seed of the first replicate)")
    return [seed + k for k in range(replicates)]


def check_kpis(kpis, where: str, name: str = "kpis") -> tuple[str, ...]:
    """KPI names the draw down test reports (``torchdem.drawdown.KPI_UNITS``); ``name``: the config key."""
    from torchdem.drawdown import KPI_UNITS

    if isinstance(kpis, (str, bytes)) or not isinstance(kpis, (list, tuple)) or not kpis:
        raise out_of_range(name, kpis, f"a non-empty list of KPI names from {sorted(KPI_UNITS)}", where)
    unknown = [k for k in kpis if k not in KPI_UNITS]
    if unknown or len(set(kpis)) != len(kpis):
        raise out_of_range(name, list(kpis), f"distinct KPI names from {sorted(KPI_UNITS)}"
                           + (f" (unknown: {unknown})" if unknown else ""), where)
    return tuple(kpis)


#: How the shipped stores hashed the execution-only settings of ``sim``
#: (``torchdem.model.EXECUTION_ONLY``): ``device`` and ``compile`` were in the block at these values;
#: the others were absent and are hashed as absent. So stores made before keep their hash, and a
#: store takes runs made on a GPU or a CPU, compiled or not, reordered or not.
HASHED_AS = {"device": "cpu", "compile": False}


#: Per config block, the settings added after stores were shipped: hashed as absent while null (their
#: old behaviour).
ABSENT_WHEN_NULL = {"run": ("max_discharge_time_s", "photo_shadow_depth_m"),
                    "sim": ("discharge_time_step_fraction",),
                    "geometry": ("gate_opening_s",)}


#: The Verlet skins (``sim.skin_fraction``) the shipped stores were hashed with, before the skin
#: joined ``torchdem.model.EXECUTION_ONLY``: the CPU profiles' 0.25 and the smoke profile's 0.5. A
#: store made at one of them is the same model's at any skin (:func:`store_hashes`).
HASHED_SKINS = (0.25, 0.5)


def config_hash(plain: Mapping[str, Any], keys: tuple[str, ...] = MODEL_KEYS) -> str:
    """Hash of the result-deciding blocks (default ``MODEL_KEYS``) of the resolved config
    (``sim``'s execution-only settings hashed as :data:`HASHED_AS` says, each block's
    :data:`ABSENT_WHEN_NULL` settings left out while null): the hash a new store is made with."""
    return _digest(plain, keys)


def store_hashes(plain: Mapping[str, Any], keys: tuple[str, ...] = MODEL_KEYS) -> tuple[str, ...]:
    """The hashes a store of this config's model may carry: :func:`config_hash` first, then the hashes
    the config had while ``sim.skin_fraction`` was hashed, at each of :data:`HASHED_SKINS` (where the
    ``sim`` block has the setting), which the stores made then carry."""
    sim = plain.get("sim") if "sim" in keys else None
    older = ([_digest({**plain, "sim": {**sim, "skin_fraction": skin}}, keys, kept=("skin_fraction",))
              for skin in HASHED_SKINS] if isinstance(sim, Mapping) and "skin_fraction" in sim else [])
    return tuple(dict.fromkeys([config_hash(plain, keys), *older]))


def open_store(path, plain: Mapping[str, Any], keys: tuple[str, ...] = MODEL_KEYS, **kw):
    """The :class:`~bo.campaign.store.CampaignStore` at ``path`` for this config's model: a new store
    takes :func:`config_hash`; an existing one any of :func:`store_hashes` (it keeps its own)."""
    from bo.campaign.store import CampaignStore

    first, *older = store_hashes(plain, keys)
    return CampaignStore(path, first, also_accepts=older, **kw)


def _digest(plain: Mapping[str, Any], keys: tuple[str, ...], kept: tuple[str, ...] = ()) -> str:
    """:func:`config_hash`, with the execution-only ``sim`` settings in ``kept`` hashed as they are."""
    from torchdem.model import EXECUTION_ONLY

    part = {k: plain.get(k) for k in keys}
    for block, absent in ABSENT_WHEN_NULL.items():
        if isinstance(part.get(block), Mapping):
            part[block] = {k: v for k, v in part[block].items() if not (k in absent and v is None)}
    if isinstance(part.get("sim"), Mapping):
        sim = part["sim"]
        part["sim"] = {**{k: v for k, v in sim.items() if k not in EXECUTION_ONLY or k in kept},
                       **{k: v for k, v in HASHED_AS.items() if k in sim}}
    return hashlib.sha256(json.dumps(part, sort_keys=True, default=str).encode()).hexdigest()[:16]


def measured_kpis_from(plain: Mapping[str, Any]):
    """Measured KPIs of ``condition`` from ``measured`` (null: the paper's Table 2)."""
    from torchdem.measured import load_measured

    data = load_measured(plain.get("measured"))
    condition = plain.get("condition")
    if condition not in data.names:
        raise out_of_range("condition", condition, f"a condition of the measured data {list(data.names)}",
                           f"config (measured = {plain.get('measured') or 'shipped Table 2'})")
    return data.condition(condition).kpis


def model_from(plain: Mapping[str, Any]):
    """``torchdem.model.DrawDownModel`` with the config's mixture as the one condition ``condition``."""
    from torchdem import config
    from torchdem.cli import device_from
    from torchdem.mechanisms import with_extension
    from torchdem.model import DrawDownModel

    condition = plain.get("condition")
    if not isinstance(condition, str) or not condition or "|" in condition:
        raise out_of_range("condition", condition, "a condition name such as '50-50'", "config")
    device = device_from(str(plain["sim"]["device"]), "sim.device")
    return with_extension(DrawDownModel(conditions={condition: config.mixture_from(plain["mixture"])},
                                        geometry=config.geometry_from(plain["geometry"]),
                                        settings=config.run_settings_from(plain["sim"], plain["run"]),
                                        fixed=config.contact_from(plain["contact"]), device=str(device)),
                          *config.extension_from(plain.get("extension")))


def executor_from(settings: ExecutorSettings, model, client=None, checkpoints: Path | None = None):
    """The executor running ``bo.campaign.dem.evaluate_batch`` on ``model`` (dask: on ``client``
    when given, see :func:`executor_factory`); ``checkpoints``: the directory where its batches
    checkpoint and resume (:func:`checkpoint_dir_for`)."""
    from bo.campaign.cores import CoreShare, local_cores
    from bo.campaign.dem import evaluate_batch
    from bo.campaign.executor import DaskExecutor, InProcessExecutor

    from torchdem.model import mixture_parameters

    checkpoint_dir = None if checkpoints is None else str(checkpoints)
    if settings.kind == "inprocess":
        return InProcessExecutor(functools.partial(evaluate_batch, model, checkpoint_dir=checkpoint_dir),
                                 settings.batch_size, affinity=mixture_parameters)
    # A local cluster (ours, or executor_factory's) runs on this machine: its workers share its cores.
    share = (CoreShare.create(local_cores(settings.n_workers))
             if settings.share_cores and settings.address is None else None)
    evaluate = functools.partial(evaluate_batch, model, checkpoint_dir=checkpoint_dir, core_share=share)
    try:
        if client is not None:
            return DaskExecutor(evaluate, settings.batch_size, client=client, max_in_flight=settings.max_in_flight,
                                affinity=mixture_parameters, core_share=share)
        return DaskExecutor(evaluate, settings.batch_size, address=settings.address,
                            n_workers=settings.n_workers, max_in_flight=settings.max_in_flight,
                            affinity=mixture_parameters, core_share=share)
    except BaseException:
        if share is not None:
            share.remove()
        raise


@contextlib.contextmanager
def executor_factory(settings: ExecutorSettings, checkpoints: Path | None = None):
    """``model -> executor`` for the commands that run many models (discovery, the power study:
    every hypothesis and twin is a model of its own). With ``executor=dask`` and no ``address``,
    one local cluster serves them all; a cluster per model restarted its worker processes (torch,
    the C++ kernels) for each of them. ``checkpoints``: as :func:`executor_from`'s (a batch's
    checkpoint is named by its model too, so the models share the directory)."""
    if settings.kind != "dask" or settings.address is not None:
        yield functools.partial(executor_from, settings, checkpoints=checkpoints)
        return
    from dask.distributed import Client

    from bo.campaign.executor import local_cluster

    cluster = local_cluster(settings.n_workers)
    try:
        with Client(cluster) as client:
            yield functools.partial(executor_from, settings, client=client, checkpoints=checkpoints)
    finally:
        cluster.close()


def checkpoint_dir_for(store_path: Path) -> Path:
    """Where a store's DEM batches keep their checkpoints while they run: ``<store>.runs/``
    beside the store (not committed: a checkpoint resumes a run on the machine that made it)."""
    return Path(str(store_path) + ".runs")


def requeue_failed(plain: Mapping[str, Any], store, echo=print) -> int:
    """With ``retry_failed: true``, put the store's failed runs back in the queue (after their cause
    was fixed, e.g. ``sim.retry_time_steps`` added); returns how many."""
    flag = plain.get("retry_failed", False)
    if not isinstance(flag, bool):
        raise out_of_range("retry_failed", flag, "true or false", "config")
    if not flag:
        return 0
    n = store.reset_failed()
    echo(f"retry_failed: {n} failed run(s) of {store.path} back in the queue")
    return n


def store_path_from(plain: Mapping[str, Any], out: Path) -> Path:
    """``store`` if given, else ``campaign.sqlite`` in the run directory."""
    store = plain.get("store")
    return Path(store).expanduser().resolve() if store else out / "campaign.sqlite"


def plain_config(cfg: DictConfig) -> dict:
    return OmegaConf.to_container(cfg, resolve=True)


def check_builds(model, condition: str, point: Mapping[str, float], where: str) -> None:
    """Build, without running, the DEM test of ``condition`` with the parameter set ``point``
    (``torchdem.model.DrawDownModel.test_for``), so that a name the model does not know (``mu_s_zz``,
    ``density_coke`` in a pellet-sinter mixture) or a value it refuses (a negative friction) stops a
    command before its first run instead of failing every run of a campaign. The ``ConfigError``
    starts with ``where``: what the set is and where it came from."""
    try:
        model.test_for(condition, [dict(point)])
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def check_ranges(model, condition: str, ranges: Mapping[str, Any], where: str) -> None:
    """:func:`check_builds` at the low and at the high end of every range of ``ranges``
    (``{name: (low, ..., high)}``, from the config keys ``where`` names)."""
    for end, side in ((0, "low"), (-1, "high")):
        point = {name: float(levels[end]) for name, levels in ranges.items()}
        if point:
            check_builds(model, condition, point, f"{where}: at the {side} end of every range, {point}")


def check_screening_levels(model, screening) -> None:
    """:func:`check_ranges` over a screening's levels (``ScreenSettings``: its parameter table and
    condition), as torchdem-screen and torchdem-calibrate check them before their first run."""
    table = screening.table
    check_ranges(model, screening.condition, dict(zip(table.names, zip(table.low, table.high))),
                 "screening (parameters and levels)")


# --------------------------------------------------------------------------------------------
# Screening settings
# --------------------------------------------------------------------------------------------

def parameter_table_from(cfg: Mapping[str, Any], where: str = "screening"):
    """Table 4 restricted to ``parameters`` (null: all 12), levels overridable by ``levels``
    (``{name: [low, mid, high]}``)."""
    from bo.design.dsd import ParameterTable, paper_parameter_table

    paper = paper_parameter_table()
    names = cfg.get("parameters")
    if names is None:
        names = list(paper.names)
    levels = cfg.get("levels") or {}
    if isinstance(names, (str, bytes)) or not isinstance(names, (list, tuple)) or len(names) < 2:
        raise out_of_range("parameters", names, f"a list of >= 2 names from {list(paper.names)} or null "
                           "(all 12)", where)
    if not isinstance(levels, Mapping):
        raise out_of_range("levels", levels, "a mapping name -> [low, mid, high] or null (Table 4)", where)
    unknown = [n for n in names if n not in paper.names and n not in levels]
    if unknown:
        raise out_of_range("parameters", list(names), f"names from Table 4 {list(paper.names)} (unknown: "
                           f"{unknown}; give their levels in {where}.levels)", where)
    if len(set(names)) != len(names):
        raise out_of_range("parameters", list(names), "distinct parameter names", where)
    stray = [n for n in levels if n not in names]
    if stray:
        raise out_of_range("levels", dict(levels), f"levels of parameters in {where}.parameters (not {stray})",
                           where)
    rows = []
    for n in names:
        if n in levels:
            lv = levels[n]
            if not isinstance(lv, (list, tuple)) or len(lv) != 3:
                raise out_of_range(f"levels.{n}", lv, "[low, mid, high]", where)
            rows.append((n, *lv))
        else:
            i = paper.names.index(n)
            rows.append((n, paper.low[i], paper.mid[i], paper.high[i]))
    src = f"{where}.parameters/levels (Table 4 unless given)"
    return ParameterTable(names=tuple(r[0] for r in rows), low=tuple(r[1] for r in rows),
                          mid=tuple(r[2] for r in rows), high=tuple(r[3] for r in rows), source=src)


def screen_settings_from(plain: Mapping[str, Any]):
    """Checked ``bo.screening.pipeline.ScreenSettings``; every error names the config key and the allowed range."""
    from bo.design.dsd import conference_order
    from bo.screening.pipeline import ScreenSettings

    where = "screening"
    cfg = plain.get(where)
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"config: '{where}' block is missing")
    seeds = replicate_seeds(plain)
    table = parameter_table_from(cfg, where)
    n_fake = _int(cfg.get("n_fake"), "n_fake", where, 0, "an int >= 0 (fake factors of the DSD)")
    conference_order(table.k, n_fake)  # unsupported sizes fail here, with the allowed totals
    mode = cfg.get("extension_mode")
    if mode not in ("extend", "shift"):
        raise out_of_range("extension_mode", mode, "'extend' or 'shift'", where)
    try:
        factor = float(cfg.get("extension_factor"))
    except (TypeError, ValueError):
        factor = float("nan")
    if not factor > 0 or factor == float("inf"):
        raise out_of_range("extension_factor", cfg.get("extension_factor"), "a number > 0", where)
    limits = cfg.get("limits") or {}
    if not isinstance(limits, Mapping):
        raise out_of_range("limits", limits, "a mapping {screened parameter: [low, high]} or null", where)
    checked = {}
    for name, pair in limits.items():
        if name not in table.names:
            raise out_of_range(f"limits.{name}", pair, f"limits of screened parameters {list(table.names)}", where)
        if isinstance(pair, (str, bytes, Mapping)) or not isinstance(pair, (list, tuple)) or len(pair) != 2 or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) for v in pair) or not pair[0] < pair[1]:
            raise out_of_range(f"limits.{name}", pair, "[low, high] with low < high", where)
        lo, hi = (float(v) for v in pair)
        i = table.names.index(name)
        levels = (table.low[i], table.mid[i], table.high[i])
        if sum(lo <= v <= hi for v in levels) < 2:
            raise out_of_range(f"limits.{name}", pair, "an interval holding at least two of the screened levels "
                               f"{[float(f'{v:g}') for v in levels]} (the runs outside are left out of the "
                               "Table-6 comparison)", where)
        checked[str(name)] = (lo, hi)
    return ScreenSettings(
        table=table, n_fake=n_fake, seeds=tuple(seeds), condition=str(plain.get("condition")),
        kpis=check_kpis(cfg.get("kpis"), where),
        p_threshold=_fraction(cfg.get("p_threshold"), "p_threshold", where, "a p-value in (0, 1), e.g. 0.01"),
        selection_fraction=_fraction(cfg.get("selection_fraction"), "selection_fraction", where,
                                     "a fraction in (0, 1], e.g. 0.8", include_one=True),
        stochastic_threshold=_fraction(cfg.get("stochastic_threshold"), "stochastic_threshold", where,
                                       "a share in (0, 1), e.g. 0.5"),
        extension_factor=factor, extension_mode=mode, limits=checked,
        second_order=flag(cfg.get("second_order", False), "second_order", where))
