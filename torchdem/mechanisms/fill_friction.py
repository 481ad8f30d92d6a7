"""A denser fill: the lab fills the upper box with 40 kg in four layers, and the paper does not say
how it places them or how dense the bed is. The model rains each layer from a loose stack and lets
it settle with the full frictions, which arrest the grains where they land; a bed placed by hand,
levelled or poured from low may pack denser. The fill settles with ``fill_friction`` times every
sliding and rolling friction coefficient (particles and walls), and the gate opens with the model's
own: 0 packs the densest bed these grains allow, 1 is the model as it is
(``torchdem.drawdown.FILL_FRICTION_PARAMETER``). Besides its density, the bed keeps the stresses it
settled with: a bed settled without friction presses on the walls about as hard as on the floor when
the gate opens, where a frictional one leans on its walls less.

The hypothesis: a denser bed holds a steeper stagnant zone beside the slot and puts more mass
through it per unit time (Beverloo's law scales the flow with the bulk density), so it would raise
the shear angle and the flow together, where the contact parameters trade one against the other
(docs/table2.md). Measured on the lab geometry at the Table 8 set (3 seeds each): at share 0
the bed packs 20 % denser, and of three runs one flowed with a shear angle 3 deg steeper and a flow
0.75 kg/s higher while two arched over the slot; at 0.5 it packs 5-9 % denser and neither KPI moves
beyond the runs' scatter. Prior: the whole range, 0-1 of the model's frictions."""
from torchdem.drawdown import FILL_FRICTION_PARAMETER
from torchdem.mechanisms import Mechanism

MECHANISM = Mechanism(
    name="fill_friction",
    description="the fill settles with a share of the frictions (a bed packed denser than the rained one)",
    parameters=lambda c: {FILL_FRICTION_PARAMETER: (0.0, 1.0)},
    null=lambda c: {FILL_FRICTION_PARAMETER: 1.0},
)
