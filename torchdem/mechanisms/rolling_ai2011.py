"""A rolling-resistance variant: the EPSD rolling stiffness of Ai et al. (2011),
k_r = 2.25 mu_r^2 R*^2 k_n (LIGGGHTS epsd), instead of k_r = k_t R*^2 (epsd2), with the viscous
rolling damping ratio eta_r free. Prior: eta_r 0-1 (critical damping of the rolling spring at 1)."""
import dataclasses

from torchdem.mechanisms import Mechanism


def _apply(model):
    return dataclasses.replace(model, settings=dataclasses.replace(model.settings, rolling_stiffness="ai2011"))


MECHANISM = Mechanism(
    name="rolling_ai2011",
    description="rolling stiffness of Ai et al. 2011 (epsd) with the rolling damping ratio free",
    parameters=lambda c: {"eta_r": (0.0, 1.0)},
    apply=_apply,
)
