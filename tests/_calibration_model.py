"""A known-answer stand-in for the draw down DEM, for the calibration campaign tests.

``known_kpis(params, seed, condition)`` maps contact parameters (and ``density_<material>``) to
draw down KPIs with smooth, monotone laws of the signs the paper's Table 5 reports, plus seed
noise; ``mu_r_ss`` has no effect (an inactive parameter screening must not select).
``known_measurement(true_params)`` is the noise-free "lab" at ``TRUE`` as a ``MeasuredData``
with the four conditions of the paper and a heap height, so a campaign run against it has a
known answer. ``known_batch`` is the executors' ``evaluate_batch``; with ``log_path`` it appends
one JSON line per evaluation (tests count repeats) and sleeps ``sleep_per_eval`` per task.

As a script (the kill-and-resume test runs it)::

    python tests/_calibration_model.py DB OUT LOG
"""
from __future__ import annotations

import functools
import json
import sys
import time
import zlib

import numpy as np

from bo.campaign.executor import EvalOutcome, EvalTask
from torchdem.measured import Condition, KPIValue, MeasuredData

TRUE = {"mu_s_pp": 0.62, "mu_r_pp": 0.12, "mu_s_ss": 0.78, "mu_r_ss": 0.09}
NOMINAL_DENSITY = {"pellet": 3602.4, "sinter": 3449.0}
#: the "lab" has particles this much lighter than the model's nominal densities
LAB_DENSITY_FACTOR = 0.93
SHARE = {"50-50": 0.5, "75-25": 0.75, "25-75": 0.25, "50-50-reverse": 0.5}
KPI_NAMES = ("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s", "mass_lower_box_full_kg",
             "segregation_rsd_vertical", "max_heap_height_m")
UNITS = {"angle_of_repose_deg": "deg", "shear_angle_deg": "deg", "mass_flow_rate_kg_s": "kg/s",
         "mass_lower_box_kg": "kg", "segregation_rsd_vertical": "1", "max_heap_height_m": "m"}


def known_kpis(params: dict, seed: int, condition: str, noise: bool = True, jam: bool = False,
               arch: float | None = None) -> dict[str, float]:
    """The known model's KPIs of one run. ``jam``: the pellet-rich condition's first run (75-25, seed
    0) reports a discharge that jammed (``discharge_jammed`` 1) while its KPIs stay those of the
    model, so a test sees whether the run was left out of a mean. ``arch``: the pellet-rich
    condition's fill arches over the slot wherever the pellets' sliding friction is below it (on the
    lab geometry a fill of easily sliding grains arched, ``lab_fines.sqlite``), and its runs measure
    a box that did not flow (flow 0, level surfaces 0 deg, 0.5 kg through)."""
    p = {**TRUE, **params}
    pellet = SHARE[condition.split("|")[0]]
    sinter = 1.0 - pellet
    rho = (pellet * p.get("density_pellet", NOMINAL_DENSITY["pellet"]) / NOMINAL_DENSITY["pellet"]
           + sinter * p.get("density_sinter", NOMINAL_DENSITY["sinter"]) / NOMINAL_DENSITY["sinter"])
    rng = np.random.default_rng([seed, zlib.crc32(json.dumps(sorted(params.items())).encode()),
                                 zlib.crc32(condition.encode())])
    e = (lambda s: rng.normal(0.0, s)) if noise else (lambda s: 0.0)
    friction = pellet * p["mu_s_pp"] + sinter * p["mu_s_ss"]
    if arch is not None and condition.startswith("75-25") and p["mu_s_pp"] < arch:
        return {"angle_of_repose_deg": 0.0, "shear_angle_deg": 0.0, "mass_flow_rate_full_kg_s": 0.0,
                "mass_lower_box_full_kg": 0.5, "segregation_rsd_vertical": 0.0, "max_heap_height_m": 0.0,
                "discharge_ended": 0.0, "discharge_jammed": 1.0}
    return {
        "angle_of_repose_deg": 18.0 + 12.0 * friction + 40.0 * p["mu_r_pp"] * pellet + e(0.15),
        "shear_angle_deg": 20.0 + 25.0 * friction + 20.0 * p["mu_r_pp"] + e(0.25),
        "mass_flow_rate_full_kg_s": (14.0 - 6.0 * friction) * rho + e(0.05),
        "mass_lower_box_full_kg": 38.0 - 8.0 * friction - 5.0 * p["mu_r_pp"] + e(0.08),
        "segregation_rsd_vertical": 0.25 + e(0.05),
        "max_heap_height_m": 0.12 / rho * (1.0 + 0.3 * friction) + e(0.0005),
        # the sinter-rich condition's runs stand for runs stopped before their discharge ended
        "discharge_ended": 0.0 if condition.startswith("25-75") else 1.0,
        # and, with ``jam``, the pellet-rich condition's first run for a run whose discharge jammed
        "discharge_jammed": 1.0 if jam and condition.startswith("75-25") and seed == 0 else 0.0,
    }


def known_batch(tasks: list[EvalTask], *, log_path: str | None = None,
                sleep_per_eval: float = 0.0, jam: bool = False, arch: float | None = None) -> list[EvalOutcome]:
    start = time.perf_counter()
    time.sleep(sleep_per_eval * len(tasks))
    out = [known_kpis(t.params, t.seed, t.condition, jam=jam, arch=arch) for t in tasks]
    if log_path is not None:
        with open(log_path, "a") as fh:
            fh.write("".join(json.dumps([sorted(t.params.items()), t.seed, t.condition]) + "\n" for t in tasks))
    return [EvalOutcome.success(k, time.perf_counter() - start) for k in out]


def known_measurement() -> MeasuredData:
    lab = {**TRUE, **{f"density_{m}": rho * LAB_DENSITY_FACTOR for m, rho in NOMINAL_DENSITY.items()}}
    conditions = []
    for name, pellet in SHARE.items():
        k = known_kpis(lab, 0, name, noise=False)
        kpis = {"angle_of_repose_deg": KPIValue(k["angle_of_repose_deg"], 0.3, "deg"),
                "shear_angle_deg": KPIValue(k["shear_angle_deg"], 0.5, "deg"),
                "mass_flow_rate_kg_s": KPIValue(k["mass_flow_rate_full_kg_s"], 0.1, "kg/s"),
                "mass_lower_box_kg": KPIValue(k["mass_lower_box_full_kg"], 0.15, "kg"),
                "segregation_rsd_vertical": KPIValue(0.25, 0.05, "1"),
                "max_heap_height_m": KPIValue(k["max_heap_height_m"], 0.001, "m")}
        layering = ("sinter", "pellet", "sinter", "pellet") if "reverse" in name else ("pellet", "sinter") * 2
        conditions.append(Condition(name=name, pellet_mass_fraction=pellet, layering=layering, fill_mass_kg=40.0,
                                    kpis=kpis))
    return MeasuredData(source="known-answer model of tests/_calibration_model.py", conditions=tuple(conditions))


def small_settings(**changes):
    """Campaign settings small enough for a test: 4 screened parameters, 3 replicates."""
    from bo.surrogate.acquisition import AcquisitionSettings, AdaptiveSettings
    from bo.calibration.pipeline import CalibrationSettings, SurrogateStageSettings
    from bo.design.dsd import ParameterTable
    from bo.surrogate.attainable import AttainableSettings
    from bo.surrogate.ga import GASettings
    from bo.screening.pipeline import ScreenSettings
    from bo.surrogate.gp import SurrogateConfig

    table = ParameterTable(("mu_s_pp", "mu_s_ss", "mu_r_pp", "mu_r_ss"), (0.3, 0.5, 0.04, 0.04),
                           (0.5, 0.7, 0.10, 0.10), (0.7, 0.9, 0.16, 0.16), source="test table")
    screening = ScreenSettings(table=table, n_fake=2, seeds=(0, 1, 2), condition="50-50",
                               kpis=("angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s",
                                     "mass_lower_box_full_kg", "segregation_rsd_vertical"),
                               p_threshold=0.01, selection_fraction=0.8, stochastic_threshold=0.5,
                               extension_factor=1.0, extension_mode="extend")
    surrogate = SurrogateStageSettings(
        parameters=None, bounds=None, seeds=(0, 1),
        adaptive=AdaptiveSettings(budget=40, points_per_parameter=8, q=6, target_r2=0.97, n_folds=5,
                                  cv_seeds=(0, 1), kernels=("matern52",), seed=0,
                                  acquisition=AcquisitionSettings(num_restarts=4, raw_samples=128, mc_samples=64,
                                                                  maxiter=50)),
        config=SurrogateConfig(strategy="per_kpi", n_mc_samples=64), compare_strategies=True)
    ga = GASettings(pop_size=100, n_generations=100)
    settings = CalibrationSettings(condition="50-50", screening=screening, objective_kpis=None, weights=None,
                                   surrogate=surrogate, ga=ga, ga_repetitions=2, verification_seeds=(0, 1, 2),
                                   validation_seeds=(0, 1),
                                   attainable=AttainableSettings(ga.pop_size, ga.n_generations, explain=False))
    return settings if not changes else __import__("dataclasses").replace(settings, **changes)


def campaign(db: str, out: str, log: str) -> None:
    from bo.calibration.pipeline import EXTRA_STAGES, run_calibration
    from bo.calibration.report import write_calibration_report
    from bo.campaign.executor import InProcessExecutor
    from bo.campaign.store import CampaignStore

    store = CampaignStore(db, "known-answer", extra_stages=EXTRA_STAGES)
    executor = InProcessExecutor(functools.partial(known_batch, log_path=log, sleep_per_eval=0.01), batch_size=6)
    result = run_calibration(store, executor, small_settings(), known_measurement(), out, NOMINAL_DENSITY,
                             echo=lambda s: print(s, flush=True))
    write_calibration_report(result, out)
    print(json.dumps({"calibrated": result.final_parameters}), flush=True)


if __name__ == "__main__":
    campaign(*sys.argv[1:])
