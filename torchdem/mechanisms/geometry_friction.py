"""Each particle material's sliding friction on the boxes (steel: every geometry surface, the
front and back included) free over its physical range, instead of the value the calibration left
it at. The paper's Table 5 ranks the particle-geometry frictions first for the shear angle and its
Table 8 calibrates them to 0.90 (pellets) and 0.83 (sinter). A screening over Table 4's narrow
ranges may leave one out (on the lab geometry the sinter's, ``mu_s_sg``, moved the shear angle by
+0.63 +- 0.29 deg over 0.285-0.475, below the selection's threshold), and the calibration then
keeps Table 4's 0.38 for it. The hypothesis: a particle-wall friction far above the screened range
holds the material along the walls and steepens the stagnant zone above the slot.

Prior: 0.1-1.0 for every material (Table 6 stops sliding friction at 1); the null is the
calibrated model's own values. ``front_back_walls`` gives the front and back walls a friction of
their own and leaves the other surfaces at the calibrated value; this candidate changes it on
every surface, so on the lab geometry the two differ by the side walls, floors and slot edges."""
from torchdem.mechanisms import Mechanism


def _names(c):
    return [f"mu_s_{c.letters[m]}g" for m in c.materials]


MECHANISM = Mechanism(
    name="geometry_friction",
    description="each material's sliding friction on every geometry surface free over 0.1-1.0",
    parameters=lambda c: {n: (0.1, 1.0) for n in _names(c)},
    null=lambda c: ({n: float(c.calibrated[n]) for n in _names(c)}
                    if all(n in c.calibrated for n in _names(c)) else None),
)
