"""Discovery's power study as a Hydra app (conf/power.yaml; bo/discovery/power.py).

For the null and every mechanism and effect of ``power.effects``: twin labs made with the DEM,
discovery from the true baseline on each, and the rates of detection, right cause, wrong cause
and false alarm with Wilson 95 % intervals. Resumable through the store (``store=PATH``): design
runs are shared by every twin and a finished twin is not analysed again. Writes ``power.json``,
``power.md`` and ``power.png`` (detection and right-cause rate against effect size, per
mechanism) to the run directory and prints the table.

Usage::

    python scripts/discovery_power.py store=campaigns/power_mini.sqlite
    python scripts/discovery_power.py power.labs=3 power.null_labs=10 'power.mechanisms=[cohesion]'
    python scripts/discovery_power.py store=campaigns/power_mini.sqlite power.rules=1   # the outcomes of rules 1
    python scripts/discovery_power.py store=campaigns/power_mini.sqlite power.reanalyse=true   # do they follow?
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Mapping

import hydra
from omegaconf import DictConfig

from bo.cli.common import (MODEL_KEYS, _int, checkpoint_dir_for, executor_settings_from, flag, open_store, plain_config,
                           store_path_from)
from torchdem.cli import CONF_DIR, one_line_errors
from torchdem.errors import exit_on_bad_input, out_of_range


def effects_from(plain: Mapping[str, Any], context) -> list:
    """The studied effects, each checked against its mechanism's parameters and prior."""
    from bo.discovery.power import Effect
    from torchdem.mechanisms import get

    cfg = plain.get("power") or {}
    effects = cfg.get("effects")
    if not isinstance(effects, Mapping) or not effects:
        raise out_of_range("power.effects", effects, "a mapping mechanism -> {null: {...}, values: [{...}, ...]}",
                           "config")
    chosen = cfg.get("mechanisms")
    names = list(effects) if chosen is None else list(chosen)
    out = []
    for name in names:
        if name not in effects:
            raise out_of_range("power.mechanisms", chosen, f"names with effects in power.effects {sorted(effects)}",
                               "config")
        prior = get(name, f"config power.effects.{name}").parameters(context)
        spec = effects[name]
        null, values = (spec or {}).get("null"), (spec or {}).get("values")
        if not isinstance(null, Mapping) or set(null) != set(prior):
            raise out_of_range(f"power.effects.{name}.null", null, f"a value for each of {sorted(prior)}", "config")
        steps, toward = (spec or {}).get("steps"), (spec or {}).get("toward", "high")
        if values is None and steps is not None:  # steps from the null value towards one end of the prior
            if toward not in ("high", "low"):
                raise out_of_range(f"power.effects.{name}.toward", toward, "'high' or 'low'", "config")
            if not isinstance(steps, list) or not steps or not all(isinstance(f, (int, float)) and 0 < f <= 1
                                                                   for f in steps):
                raise out_of_range(f"power.effects.{name}.steps", steps, "a non-empty list of fractions in (0, 1]",
                                   "config")
            end = {p: prior[p][1 if toward == "high" else 0] for p in prior}
            values = [{p: float(null[p]) + f * (end[p] - float(null[p])) for p in prior} for f in steps]
        if not isinstance(values, list) or not values:
            raise out_of_range(f"power.effects.{name}.values", values, "a non-empty list of {parameter: value} "
                               "(or steps: [fractions] with toward: high|low)", "config")
        for k, v in enumerate(values):
            where = f"power.effects.{name}.values[{k}]"
            if not isinstance(v, Mapping) or set(v) != set(prior):
                raise out_of_range(where, v, f"a value for each of {sorted(prior)}", "config")
            for p, x in v.items():
                lo, hi = prior[p]
                if not (isinstance(x, (int, float)) and min(lo, null[p]) - 1e-9 <= x <= hi + 1e-9):
                    raise out_of_range(f"{where}.{p}", x, f"a value in the prior [{lo:g}, {hi:g}]", "config")
            fraction = max(abs(float(v[p]) - float(null[p])) / (prior[p][1] - prior[p][0]) for p in v)
            out.append(Effect(name, {p: float(x) for p, x in v.items()}, fraction))
    return out


def run(plain: Mapping[str, Any], out: Path, echo=print) -> dict:
    from bo.cli.calibrate import calibration_model_from
    from bo.cli.common import executor_factory
    from bo.cli.discover import calibrated_from, discovery_settings_from
    from bo.discovery.pipeline import discovery_stages
    from bo.discovery.power import power_stages, power_summary, run_power_study, tabulate
    from torchdem.measured import load_measured
    from torchdem.mechanisms import model_context

    cfg = plain.get("power") or {}
    settings = discovery_settings_from(plain)
    executor_settings = executor_settings_from(plain.get("executor") or {})
    numbers = {k: _int(cfg.get(k), f"power.{k}", "config", low, allowed) for k, low, allowed in (
        ("labs", 1, "an int >= 1"), ("null_labs", 0, "an int >= 0"), ("lab_replicates", 2, "an int >= 2"),
        ("lab_seed", 0, "an int >= 0"), ("discovery_seed", 0, "an int >= 0"))}
    reanalysing = flag(cfg.get("reanalyse", False), "power.reanalyse", "config")
    target = float(cfg.get("target", 0.8))
    if not 0 < target <= 1:
        raise out_of_range("power.target", target, "a share in (0, 1]", "config")
    data = plain.get("data") if plain.get("data") is not None else plain.get("measured")
    template = load_measured(data)
    model, _ = calibration_model_from({**plain, "measured": data}, template)
    baseline, source = calibrated_from(plain, model.fixed)
    effects = effects_from(plain, model_context(model, baseline))
    names = sorted({e.mechanism for e in effects})
    store = open_store(store_path_from(plain, out), plain, MODEL_KEYS + ("measured", "calibration"),
                       allow_config_mismatch=bool(plain.get("allow_config_mismatch")),
                       extra_stages=discovery_stages() + power_stages(names))
    if reanalysing:
        return reanalyse_report(store, model, baseline, template, effects, settings, numbers, out, echo)
    echo(f"power study: {len(effects)} effects x {numbers['labs']} labs + {numbers['null_labs']} null labs; "
         f"baseline from {source}; store {store.path}")
    started = time.perf_counter()
    with executor_factory(executor_settings, checkpoints=checkpoint_dir_for(store.path)) as executor_for:
        outcomes = run_power_study(store, executor_for, model, baseline, template, effects, settings,
                                   labs=numbers["labs"], null_labs=numbers["null_labs"],
                                   lab_replicates=numbers["lab_replicates"], lab_seed=numbers["lab_seed"],
                                   discovery_seed=numbers["discovery_seed"], echo=echo, rules=cfg.get("rules"))
    rows = tabulate(outcomes, effects)
    summary = power_summary(rows, target)
    wall = time.perf_counter() - started
    computed = store.counts(computed_only=True)["done"]
    total = store.counts()["done"]
    from bo.discovery.pipeline import rules_of

    rules = rules_of(settings) if cfg.get("rules") is None else cfg.get("rules")
    files = write_power_report(rows, summary, out, cost={"dem_runs_computed": computed, "dem_runs_used": total,
                                                          "wall_time_s": round(wall, 1), "verdict_rules": rules})
    echo(files["md"].read_text())
    return {"files": {k: str(v) for k, v in files.items()}, "computed": computed, "used": total}


def reanalyse_report(store, model, baseline, template, effects, settings, numbers: Mapping[str, int], out: Path,
                     echo=print) -> dict:
    """``power.reanalyse``: every stored twin analysed again without a DEM run (``bo.discovery.power.reanalyse``);
    writes reanalysis.json and reanalysis.md and prints the count of each status."""
    from collections import Counter

    from bo.discovery.pipeline import rules_of
    from bo.discovery.power import reanalyse

    started = time.perf_counter()
    rows = reanalyse(store, model, baseline, template, effects, settings, labs=numbers["labs"],
                     null_labs=numbers["null_labs"], lab_replicates=numbers["lab_replicates"],
                     lab_seed=numbers["lab_seed"], discovery_seed=numbers["discovery_seed"], echo=echo)
    counts = Counter(r["status"] for r in rows)
    wall = round(time.perf_counter() - started, 1)
    lines = ["# Power study analysed again from its store", "",
             f"Verdict rules {rules_of(settings)}, {len(rows)} stored twins, wall time {wall} s, no DEM run: "
             + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) + ".", ""]
    lines += [f"- {r['mechanism']} effect {r['effect_index']} lab {r['lab']}: {r['status']}"
              + (f", {r['runs']} runs" if "runs" in r else "")
              + "".join(f"; {k} {v[0]} -> {v[1]}" for k, v in r.get("changed", {}).items())
              for r in rows if r["status"] != "same"]
    out.mkdir(parents=True, exist_ok=True)
    (out / "reanalysis.json").write_text(json.dumps({"rows": rows, "wall_time_s": wall}, indent=2, default=str) + "\n")
    (out / "reanalysis.md").write_text("\n".join(lines) + "\n")
    echo("\n".join(lines))
    return {"counts": dict(counts), "files": {"md": str(out / "reanalysis.md"), "json": str(out / "reanalysis.json")}}


def _pct(rate) -> str:
    r, lo, hi = rate
    return "-" if not math.isfinite(r) else f"{100 * r:.0f} % ({100 * lo:.0f}-{100 * hi:.0f})"


def write_power_report(rows, summary, out: Path, cost: Mapping[str, float]) -> dict[str, Path]:
    from bo.discovery.power import NULL, rows_to_json
    from bo.report.plots import write_power_plot

    out.mkdir(parents=True, exist_ok=True)
    lines = ["# Discovery power study", "",
             f"DEM runs computed {cost['dem_runs_computed']}, used {cost['dem_runs_used']} (the rest shared), "
             f"wall time {cost['wall_time_s']} s. Verdict rules {cost.get('verdict_rules', '-')} "
             "(bo.discovery.pipeline.VERDICT_RULES).", "",
             "| mechanism | effect | fraction of prior | labs | detected | right cause | other cause (which) | "
             "no cause: tied, unresolved |",
             "| --- | --- | ---: | ---: | --- | --- | --- | --- |"]
    for r in rows:
        which = ", ".join(f"{k} {v}" for k, v in r.wrong_causes.items()) or "-"
        lines.append(f"| {r.mechanism} | {r.effect} | {r.fraction:.2f} | {r.n} | {_pct(r.detection)} | "
                     f"{'-' if r.mechanism == NULL else _pct(r.right_rate)} | {_pct(r.wrong_rate)} ({which}) | "
                     f"{r.tied}, {r.unresolved} |")
    lines.append("")
    for name, s in summary.items():
        if name == NULL:
            lines.append(f"- null: false alarms (a cause named) {_pct(s['false_alarm'])} of {s['n']} labs; "
                         f"discrepancy detected {_pct(s['detection'])}")
        elif s["reached"] is None:
            lines.append(f"- {name}: the right cause is not named in 80 % of labs at any studied effect")
        else:
            r = s["reached"]
            lines.append(f"- {name}: named right in {_pct(r['right'])} at {r['effect']} ({r['fraction']:.2f} of the "
                         f"prior); misattributed in {_pct(r['wrong'])}")
    files = {"md": out / "power.md", "json": out / "power.json", "png": out / "power.png"}
    files["md"].write_text("\n".join(lines) + "\n")
    files["json"].write_text(json.dumps({"rows": rows_to_json(rows), "summary": summary, "cost": dict(cost)},
                                        indent=2, default=str) + "\n")
    write_power_plot(rows, files["png"])
    return files


@hydra.main(config_path=CONF_DIR, config_name="power", version_base="1.3")
@one_line_errors("discovery_power")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    run(plain_config(cfg), Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    exit_on_bad_input("discovery_power.py", main)
