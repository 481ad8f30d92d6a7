"""The outlet's width free: the paper's text does not state the box's dimensions (its Fig. 2 does),
so ``conf/geometry/drawdown_full.yaml`` derives the slot from the steady flow with Beverloo's law
(W = C rho_b sqrt(g) L (b - k d)^1.5, C = 1.0, k = 2, d = 12 mm: b = 65 mm). Beverloo's constants
for slots span C 0.8-1.03 and k 1.5-3 in the literature, which put the same 10.3 kg/s through a
slot of 57-83 mm, so the lab's slot is known to about -12/+27 %. Prior: 0.85-1.3 of the model's
outlet width (55-85 mm for the lab box).

A wider slot discharges faster and, around it, leaves narrower wedges in the upper box, so the
lower box's mass rises unless the shear angle steepens: on the lab geometry the calibrated set
matched the lower box with a shear angle 6 degrees below the lab's and a flow 13 % low. One
ensemble has one set of walls, so each design point runs as an ensemble of its own
(``bo.campaign.dem.evaluate_batch``)."""
from torchdem.mechanisms import Mechanism

LOW, HIGH = 0.85, 1.3  # of the model's outlet width


def _parameters(c):
    b = c.geometry["outlet_width"]
    return {"geometry_outlet_width": (round(LOW * b, 6), round(min(HIGH * b, 0.95 * c.geometry["upper_width"]), 6))}


def _unavailable(c):
    if "outlet_width" not in c.geometry:
        return "the model's context gives no box lengths"
    return None


MECHANISM = Mechanism(
    name="outlet_width",
    description="width of the upper box's outlet slot free (the paper's text does not give it)",
    parameters=_parameters,
    available=_unavailable,
    null=lambda c: {"geometry_outlet_width": float(c.geometry["outlet_width"])},
)
