"""Make a synthetic measurement ("digital twin" lab data) with the DEM itself, at known parameters.

Why: a calibration can only be checked against data whose true parameters are known. The CPU
profile of ``torchdem-calibrate`` runs the small draw down box (``+experiment=mini``), whose KPIs
do not compare with the paper's 40 kg lab box, so it calibrates against this file instead: the
same four conditions as the paper (50-50, 75-25, 25-75, 50-50 reverse), each run with the DEM
at the parameters below for ``--replicates`` seeds, written in the measured-data format
(``torchdem.measured``: mean and 95 % CI half-width ``t(0.975, n-1) s / sqrt(n)`` per KPI) with
the generating parameters in ``source`` and ``notes``. The particle densities are the model's
times ``--density-factor`` (default 0.93, the paper's H_DEM/H_Exp): the calibration model uses
the nominal densities, so its bulk density check has a real mismatch to find.

Usage::

    python scripts/make_twin_measurement.py --out torchdem/data/mini_box_twin.json \
        [--replicates 5] [--seed 100] [-- extra Hydra overrides of conf/calibrate.yaml]

Prints the KPI table it wrote.
"""
from __future__ import annotations

import argparse
import json
import time

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from bo.discovery.power import LAB_KPIS, twin_kpis
from torchdem.model import DENSITY_PREFIX
from torchdem.cli import CONF_DIR
from torchdem.measured import load_measured
from torchdem.errors import exit_on_bad_input

#: The "true" contact parameters of the twin (inside the CPU profile's screening ranges, away
#: from the reference values of Table 4).
TRUE_PARAMETERS = {"mu_s_pp": 0.62, "mu_r_pp": 0.12, "mu_s_ss": 0.78, "mu_r_ss": 0.10}


def main(argv=None) -> None:
    from bo.cli.calibrate import calibration_model_from

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--replicates", type=int, default=5)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--density-factor", type=float, default=0.93)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of conf/calibrate.yaml")
    args = parser.parse_args(argv)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = OmegaConf.to_container(compose(config_name="calibrate", overrides=["measured=null", *args.overrides]),
                                       resolve=True)
    paper = load_measured()  # conditions (fractions, layering) of the paper
    model, densities = calibration_model_from(plain, paper)
    params = {**TRUE_PARAMETERS, **{DENSITY_PREFIX + m: rho * args.density_factor for m, rho in densities.items()}}
    seeds = [args.seed + k for k in range(args.replicates)]
    conditions = {}
    started = time.perf_counter()
    for name in paper.names:
        result = model.test_for(name, [params]).run(replicates=len(seeds), seeds=seeds, device=model.device)
        measured = twin_kpis({dem: result.kpi_table(dem) for dem in LAB_KPIS})
        missing = [dem for dem, (lab, _) in LAB_KPIS.items() if lab not in measured]
        if missing:
            raise SystemExit(f"{name}: {missing} measured in fewer than 2 of {len(seeds)} replicates; need >= 2")
        kpis = {lab: {"mean": round(v.mean, 6), "ci95": round(v.ci95, 6)} for lab, v in measured.items()}
        c = paper.condition(name)
        conditions[name] = {"description": f"DEM twin of {c.description or name}", "pellet_mass_fraction":
                            c.pellet_mass_fraction, "layering": list(c.layering),
                            "fill_mass_kg": round(float(result.kpi_table('fill_mass_full_kg').mean()), 4),
                            "replicates": len(seeds), "kpis": kpis}
        print(f"{name}: " + ", ".join(f"{k} {v['mean']:.4g} +- {v['ci95']:.2g}" for k, v in kpis.items()), flush=True)
    model_desc = {k: plain[k] for k in ("geometry", "sim", "run")}
    data = {
        "format": "torchdem-measured-data/1",
        "source": (f"Synthetic measurement made by scripts/make_twin_measurement.py with torchdem itself (not a lab): "
                   f"the draw down model of `torchdem-calibrate {' '.join(args.overrides) or '(profile=cpu)'}` run at "
                   f"{json.dumps(TRUE_PARAMETERS)} with particle densities x {args.density_factor} "
                   f"({', '.join(f'{m} {rho * args.density_factor:.1f} kg/m^3' for m, rho in densities.items())}), "
                   f"other contact parameters as the model's, seeds {seeds}."),
        "units": {"max_heap_height_m": "m"},
        "notes": ["The 95 % CI half-width of every KPI is t(0.975, n-1) s / sqrt(n) over the replicates.",
                  "mass_flow_rate_kg_s and mass_lower_box_kg are the slice's values scaled to the full depth of the "
                  "simulated box (the DEM's *_full_* KPIs).",
                  f"model: {json.dumps(model_desc, default=str)}",
                  f"true parameters: {json.dumps(params)}",
                  f"wall time {time.perf_counter() - started:.0f} s"],
        "conditions": conditions,
    }
    with open(args.out, "w") as fh:
        json.dump(data, fh, indent=2)
        fh.write("\n")
    load_measured(args.out)  # the file must read back
    print(f"wrote {args.out}")


if __name__ == "__main__":
    exit_on_bad_input("make_twin_measurement.py", main)
