"""Run some of a campaign's pending DEM runs on a machine that cannot open its store (a GPU host with
no shared disk), and bring their outcomes back.

A campaign store is shared by processes of one machine, or of machines that share its disk. A GPU
lent for minutes, with nothing but a copy of the repository, is neither. This script takes chosen
tasks out of the store under a lease, runs them there, and records what comes back:

    # here: lease tasks 11-13 to "h200" for 2 h and write them to a file that travels
    python scripts/offload_runs.py lease campaigns/table2/lab_fines.sqlite profile=lab_fines \\
        --tasks 11 12 13 --owner h200:offload --hours 2 --out offload/tasks_60.json
    # there: run them as one ensemble, on the GPU, checkpointing as a campaign does
    python scripts/offload_runs.py run offload/tasks_60.json sim.device=cuda sim.compile=true \\
        --out $OUT/done_60.json --checkpoints /tmp/ckpt
    # here: record the outcomes in the store (the campaign, if running, takes them as finished)
    python scripts/offload_runs.py record campaigns/table2/lab_fines.sqlite done_60.json
    # or, when they did not come back: the campaign takes them again
    python scripts/offload_runs.py release campaigns/table2/lab_fines.sqlite --tasks 11 12 13 --owner h200:offload

``run`` composes the same config as the campaign (``calibrate`` with the tasks file's overrides and
the ones given, which may only change execution settings: ``sim.device``, ``sim.compile``, ...) and
refuses to run when its hash differs from the store's. The tasks of a file must share one condition;
tasks with different box lengths run as one ensemble per set of lengths, in turn
(``bo.campaign.dem.evaluate_batch``). A campaign running beside a lease leaves the leased tasks alone
until the lease ends; ``record`` writes them as done (or failed) whatever the lease.
"""
from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from bo.campaign.dem import evaluate_batch
from bo.campaign.executor import EvalOutcome, EvalTask
from bo.campaign.progress import config_hash_of
from bo.campaign.store import CampaignStore
from bo.cli.common import MODEL_KEYS, model_from, open_store, plain_config, store_hashes
from torchdem.errors import ConfigError, exit_on_bad_input

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")
#: The config blocks a store is keyed by, per command whose model ``model_from`` builds: the stores of
#: ``torchdem-calibrate`` and of ``scripts/probe_sets.py`` (``bo.cli.calibrate``). A discovery's store
#: also hashes its calibration, and a study's runs build other models: neither is offered.
HASHED = {"calibrate": MODEL_KEYS + ("measured",)}


def compose_plain(overrides: list[str], command: str = "calibrate") -> dict:
    """The resolved config of ``command`` (its ``conf/<command>.yaml``) with ``overrides``."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return plain_config(compose(command, overrides=list(overrides)))


def lease(args) -> None:
    plain = compose_plain(args.overrides, args.command_of_store)
    store = open_store(args.store, plain, HASHED[args.command_of_store])
    digest = store.config_hash
    tasks = store.lease(args.tasks, args.owner, time.time() + 3600.0 * args.hours)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"store": str(args.store), "command": args.command_of_store, "config_hash": digest,
                               "overrides": args.overrides,
                               "tasks": [{"task_id": t.task_id, "params": t.params, "seed": t.seed,
                                          "condition": t.condition} for t in tasks]}, indent=1))
    print(f"leased {[t.task_id for t in tasks]} of {args.store} to {args.owner} for {args.hours:g} h; "
          f"tasks in {out}")


def run(args) -> None:
    spec = json.loads(Path(args.tasks_file).read_text())
    plain = compose_plain([*spec["overrides"], *args.overrides], spec["command"])
    hashes = store_hashes(plain, HASHED[spec["command"]])
    if spec["config_hash"] not in hashes:
        raise ConfigError(f"{args.tasks_file}: the overrides {args.overrides} change the model (config hash "
                          f"{hashes[0]} against the store's {spec['config_hash']}); give only "
                          "execution settings (sim.device, sim.compile, sim.reorder_every, sim.skin_fraction)")
    model = model_from(plain)
    tasks = [EvalTask(t["params"], t["seed"], t["condition"], t["task_id"]) for t in spec["tasks"]]
    started, shown = time.perf_counter(), [-1.0]

    def progress(simulated: float, wall: float) -> None:
        if simulated - shown[0] >= args.every:
            shown[0] = simulated
            print(f"[{socket.gethostname()}] tasks {[t.task_id for t in tasks]}: {simulated:.2f} s simulated "
                  f"in {wall:.0f} s", flush=True)

    outcomes = evaluate_batch(model, tasks, args.checkpoints, progress=progress)
    wall = time.perf_counter() - started
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({
        "config_hash": spec["config_hash"], "host": socket.gethostname(), "device": str(model.device),
        "wall_s": wall, "outcomes": [{"task": {"task_id": t.task_id, "params": t.params, "seed": t.seed,
                                               "condition": t.condition},
                                      "kpis": o.kpis, "error": o.error, "wall_time": o.wall_time}
                                     for t, o in zip(tasks, outcomes)]}, indent=1, default=_not_json))
    for t, o in zip(tasks, outcomes):
        print(f"task {t.task_id}: " + (o.error if not o.ok else ", ".join(
            f"{k} {o.kpis[k]:.4g}" for k in ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s",
                                              "mass_lower_box_full_kg"))) + f" ({o.wall_time:.0f} s)")


def _not_json(value):
    raise TypeError(f"not JSON: {value!r}")


def record(args) -> None:
    for path in args.outcomes:
        done = json.loads(Path(path).read_text())
        store = CampaignStore(args.store, done["config_hash"])
        finished = [(EvalTask(o["task"]["params"], o["task"]["seed"], o["task"]["condition"], o["task"]["task_id"]),
                     EvalOutcome(o["kpis"], o["error"], float(o["wall_time"]))) for o in done["outcomes"]]
        written = store.record(finished)
        print(f"{path}: {written} of {len(finished)} outcomes recorded in {args.store} "
              f"(run on {done['host']}, {done['device']})")


def release(args) -> None:
    store = CampaignStore(args.store, config_hash_of(args.store, "offload_runs.py release"))
    given = store.release(args.tasks, owner=args.owner)
    print(f"{given} of {len(args.tasks)} tasks leased to {args.owner} are pending again in {args.store}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("lease", help="lease pending tasks of a store and write them to a file")
    p.add_argument("store", type=Path)
    p.add_argument("overrides", nargs="*", help="the campaign's config overrides, e.g. profile=lab_fines")
    p.add_argument("--tasks", type=int, nargs="+", required=True, help="task ids (the store's task_id)")
    p.add_argument("--command", dest="command_of_store", choices=sorted(HASHED), default="calibrate",
                   help="the command whose store it is (it decides the config hash)")
    p.add_argument("--owner", default="offload:1", help="'host:name' the store shows as running them")
    p.add_argument("--hours", type=float, default=2.0, help="how long no claim of the store takes them")
    p.add_argument("--out", required=True)
    p.set_defaults(func=lease)
    p = sub.add_parser("run", help="run a tasks file's tasks and write their outcomes")
    p.add_argument("tasks_file")
    p.add_argument("overrides", nargs="*", help="execution settings only, e.g. sim.device=cuda sim.compile=true")
    p.add_argument("--out", required=True)
    p.add_argument("--checkpoints", default=None, help="checkpoint directory (resumes a batch found there)")
    p.add_argument("--every", type=float, default=0.25, help="print progress every this many simulated s")
    p.set_defaults(func=run)
    p = sub.add_parser("record", help="record outcomes files in the store")
    p.add_argument("store", type=Path)
    p.add_argument("outcomes", nargs="+")
    p.set_defaults(func=record)
    p = sub.add_parser("release", help="make leased tasks whose outcomes will not come back pending again")
    p.add_argument("store", type=Path)
    p.add_argument("--tasks", type=int, nargs="+", required=True)
    p.add_argument("--owner", required=True, help="the lease's owner")
    p.set_defaults(func=release)
    args = parser.parse_args(argv)
    try:
        args.func(args)
    except ConfigError as exc:
        sys.exit(f"offload_runs: {exc}")


if __name__ == "__main__":
    exit_on_bad_input("offload_runs.py", main)
