"""How fast bodies move while the rained fill lands: the fastest body of one draw down member
every 50 steps of the fill, at one or more time-step scales, and whether the blow-up guard fired.

The fill is the stiffest moment of a run: soft particles (G = 1e6 Pa) rained from a loose stack
land at ~4 m/s and overlap deeply, so a time step that is stable for the flow can be marginal
there. A landing bed that throws bodies faster than the falling fill (a few m/s) is the sign of
it; ``sim.retry_time_steps`` runs a campaign run that blows up again at a shorter step.

    python scripts/fill_landing.py --params '{"lobe_spacing_sinter": 0.15, "e_ss": 0.263}' \\
        --scales 1 0.8 -- profile=lab            # Hydra overrides of the calibrate config after --

Prints, per scale, the time step, the times where the fastest body moved faster than
``--report-above`` m/s, the largest speed seen and the guard's message if it fired, and how far the
fill is from rest at its end (as the gate opens, with ``--until`` 0): its fastest body and how many
bodies move faster than the photos' rest speed (``torchdem.drawdown.AT_REST_SPEED_M_S``). The lab
opens its gate on a fill at rest; ``run.fill_time_s`` sets when the model's opens:

    python scripts/fill_landing.py --condition 50-50-reverse --scales 1 --params '{...}' -- profile=lab_priors \
        run.fill_time_s=1.2
"""
from __future__ import annotations

import argparse
import json
import time

import torch
from hydra import compose, initialize_config_dir

from bo.cli.calibrate import calibration_model_from
from bo.cli.common import plain_config
from torchdem.cli import CONF_DIR
from torchdem.drawdown import AT_REST_SPEED_M_S
from torchdem.errors import BlowUpError, exit_on_bad_input
from torchdem.measured import load_measured
from torchdem.simulation import Simulation


def landing(model, condition: str, params: dict, seed: int, scale: float, until: float, every: int = 50):
    """``(dt, [(t, speed, body id)], error or None, end)``: the fastest body every ``every`` steps of
    one member until ``until`` s (default: the fill's end), the guard raising, and at the last step
    ``end = (t, fastest speed m/s, bodies faster than AT_REST_SPEED_M_S, active bodies)``."""
    test = model.test_for(condition, [params], isolate=False, time_step_scale=scale)
    system, state, _ = test.build([seed], [0])
    sim = Simulation(system, state, test.settings.guards, reorder_every=test.settings.reorder_every)
    trace = []

    def fastest(s: Simulation) -> None:
        b = s.state.bodies
        speed = b.velocity.norm(dim=-1) * b.active
        k = int(speed[0].argmax())
        trace.append((s.time, float(speed[0, k]), int(s.state.body_id[0, k])))

    error = None
    try:
        sim.run_until(until if until > 0 else test.settings.fill_time, callback=fastest, callback_every=every)
    except BlowUpError as err:
        error = str(err)
    b = sim.state.bodies
    speed = (b.velocity.norm(dim=-1) * b.active)[0]
    end = (sim.time, float(speed.max()), int((speed > AT_REST_SPEED_M_S).sum()), int(b.active[0].sum()))
    return float(system.dt), trace, error, end


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--params", default="{}", help="JSON of the member's parameters (contact, lobe_spacing_*, ...)")
    parser.add_argument("--condition", default="50-50")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.8], help="factors of the time step")
    parser.add_argument("--until", type=float, default=0.0, help="simulated time, s (0: the fill's end)")
    parser.add_argument("--report-above", type=float, default=6.0, help="m/s")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the calibrate config, e.g. profile=lab")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        plain = plain_config(compose("calibrate", overrides=list(args.overrides)))
    model, _ = calibration_model_from(plain, load_measured(plain.get("measured")))
    params = json.loads(args.params)
    for scale in args.scales:
        started = time.perf_counter()
        dt, trace, error, (t_end, v_end, moving, active) = landing(model, args.condition, params, args.seed, scale,
                                                                   args.until)
        fast = [f"{t:.3f} s {v:.1f} m/s (body {k})" for t, v, k in trace if v > args.report_above]
        top = max((v for _, v, _ in trace), default=float("nan"))
        print(f"time step x {scale:g} ({dt * 1e6:.1f} us): fastest body {top:.2f} m/s over the trace; "
              f"{time.perf_counter() - started:.0f} s wall", flush=True)
        print("  above {:g} m/s: {}".format(args.report_above, "; ".join(fast) if fast else "none"))
        print(f"  at t = {t_end:.3f} s: fastest body {v_end:.3f} m/s, {moving} of {active} bodies faster than "
              f"{AT_REST_SPEED_M_S:g} m/s")
        if error:
            print(f"  blew up: {error}")


if __name__ == "__main__":
    exit_on_bad_input("fill_landing.py", main)
