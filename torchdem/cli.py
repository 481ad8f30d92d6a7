"""Command-line entry points (Hydra apps). Thin ``main()`` functions that turn a config into
typed objects and call plain library functions; library code never sees a DictConfig.
"""
from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Callable

import hydra
import torch
from omegaconf import DictConfig

from torchdem.errors import ConfigError, exit_on_bad_input, out_of_range
from torchdem.simulation import GuardSettings

CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def one_line_errors(command: str) -> Callable:
    """Decorate a Hydra task function so that bad input ends the command with one line,
    ``<command>: error: <message>`` on stderr, and exit status 2 instead of a traceback.
    ``HYDRA_FULL_ERROR=1`` re-raises (the traceback). Put it under ``@hydra.main``."""

    def wrap(task: Callable) -> Callable:
        @functools.wraps(task)
        def run(cfg):
            return exit_on_bad_input(command, lambda: task(cfg))
        return run

    return wrap


def dtype_from(name: str, source: str) -> torch.dtype:
    if name not in DTYPES:
        raise ConfigError(f"{source}: dtype = {name!r}; expected one of {sorted(DTYPES)}")
    return DTYPES[name]


def device_from(name: str, source: str) -> torch.device:
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ConfigError(f"{source}: device = {name!r} is not a torch device ({exc})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"{source}: device = {name!r} but CUDA is not available on this machine; use sim=cpu")
    return device


def guards_from(cfg) -> GuardSettings:
    return GuardSettings(check_every=int(cfg.check_every), max_speed=float(cfg.max_speed),
                         energy_tolerance=float(cfg.energy_tolerance), on_blowup=str(cfg.on_blowup)).validate("sim.guards")


@hydra.main(config_path=CONF_DIR, config_name="demo", version_base="1.3")
@one_line_errors("torchdem-demo")
def demo_main(cfg: DictConfig) -> None:
    """Pour spheres into a box, settle, report what happened (the engine's `make run`)."""
    from hydra.core.hydra_config import HydraConfig

    from torchdem.demo import PourSettings, pour_and_settle

    from torchdem import config

    out = Path(HydraConfig.get().runtime.output_dir)
    device = device_from(cfg.sim.device, "sim.device")
    contact = config.single_contact_from(cfg.contact)
    settings = PourSettings(
        n_side=int(cfg.pour.n_side), layers=int(cfg.pour.layers), radii=tuple(cfg.pour.radii_m),
        box=tuple(cfg.pour.box_m), duration=float(cfg.pour.duration_s), ensemble=int(cfg.ensemble),
        seed=int(cfg.seed), shear_modulus=float(cfg.material.shear_modulus_pa),
        poisson_ratio=float(cfg.material.poisson_ratio), density=float(cfg.material.density_kg_m3),
        mu_s=contact["mu_s"], mu_r=contact["mu_r"], restitution=contact["restitution"],
        rolling_damping=contact["rolling_damping"],
        time_step_fraction=float(cfg.sim.time_step_fraction), skin_fraction=float(cfg.sim.skin_fraction),
        rolling_stiffness=str(cfg.sim.rolling_stiffness), vtk_interval=int(cfg.output.vtk_interval),
    )
    report = pour_and_settle(settings, device=device,
                             dtype=dtype_from(cfg.sim.dtype, "sim.dtype"), compile=bool(cfg.sim.compile),
                             guards=guards_from(cfg.sim.guards), output_dir=out)
    (out / "report.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    print(f"wrote {out / 'report.json'}")


@hydra.main(config_path=CONF_DIR, config_name="simulate", version_base="1.3")
@one_line_errors("torchdem-simulate")
def simulate_main(cfg: DictConfig) -> None:
    """One draw down test (``replicates`` members in one ensemble) -> kpis.json, CSV, PNG."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf
    from tqdm import tqdm

    from torchdem import config
    from torchdem.drawdown import DrawDownTest
    from torchdem.mechanisms import with_extension
    from torchdem.model import DrawDownModel
    from torchdem.simulate import format_summary, simulate_drawdown

    plain = OmegaConf.to_container(cfg, resolve=True)
    out = Path(HydraConfig.get().runtime.output_dir)
    # every check that needs no simulation comes before the progress bar and the fill
    device = device_from(str(plain["sim"]["device"]), "sim.device")
    replicates = int(cfg.replicates)
    if replicates < 1:
        raise out_of_range("replicates", replicates, "an integer >= 1", "config")
    mixture = config.mixture_from(plain["mixture"])
    test = DrawDownTest(mixture, config.geometry_from(plain["geometry"]),
                        config.contact_from(plain["contact"]), config.run_settings_from(plain["sim"], plain["run"]))
    name, values = config.extension_from(plain.get("extension"))
    if name is not None or values:  # the model holds the mixture as measured: a mechanism may act on its fines
        model = with_extension(DrawDownModel({"run": mixture}, test.geometry, test.settings,
                                             fixed=test.parameter_sets[0], device=str(device)), name, values)
        test = model.test_for("run", [{}], isolate=False)
    seeds = [int(cfg.seed) + k for k in range(replicates)]
    bar = tqdm(total=round(test.total_time, 3), unit="sim-s", disable=not cfg.output.progress,
               bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} simulated s [{elapsed}<{remaining}, {postfix}]")

    def progress(simulated: float, wall: float) -> None:
        bar.n = round(min(simulated, test.total_time), 3)
        bar.set_postfix_str(f"{simulated / max(wall, 1e-9):.3f} sim-s/s", refresh=False)
        bar.refresh()

    vtk = cfg.output.vtk_interval_s
    report = simulate_drawdown(test, seeds, out, device=device,
                               images=bool(cfg.output.images), vtk_interval_s=None if vtk is None else float(vtk),
                               checkpoint_every_s=float(cfg.output.checkpoint_every_s), progress=progress)
    bar.close()
    print(format_summary(report))
    print(f"wrote {out / 'kpis.json'}")


if __name__ == "__main__":  # pragma: no cover
    demo_main()
