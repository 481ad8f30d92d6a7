"""Fines kept: the share ``fines_kept_<material>`` of each sieve class below the runs' fines cut
(``sim.fines_cut_mm``) kept as sieved instead of scalped into the class at the cut
(``torchdem.mixture.scalp_sieve``). Prior: 0 (the model as calibrated, all scalped) to 1 (the sieve as
measured); the null is 0.

Why it is a candidate: scalping keeps a material's mass but carries its fines on coarser grains, so
the particle count and the smallest sphere (which sets the time step) shrink; on 2 cores that is
what makes a lab-scale run affordable. It also removes what fines do: they fill the voids among
coarse grains, so the fill packs denser and the face a shear band cuts through the upper box
stands steeper, and they thin Beverloo's empty annulus at the slot's edges, so the flow rises. On
the lab geometry the paper's sinter scalped below 10 mm (59.5 % of its mass) flattened the face by
1.2-4.1 deg and steepened the heap by about 1 deg against the sieve as measured
(campaigns/table2/probe_fines.yaml), while the periodic slice had not shown it. The paper's own
time step says it ran the fines.

A run with any share kept has the fine classes' spheres, so its step is the full sieve's (the
smallest lobe at 5.6 mm against 10 mm: 1.79x shorter), and the body count grows with the share
(2.1-2.6x at 1). The mechanism changes no other setting."""
from torchdem.mechanisms import Mechanism

LOW, HIGH = 0.0, 1.0


def scalped_materials(c) -> tuple[str, ...]:
    """The materials whose measured sieve reaches below the runs' fines cut, in mixture order."""
    if c.fines_cut is None:
        return ()
    return tuple(m for m in c.materials if c.smallest_size.get(m, c.fines_cut) < c.fines_cut - 1e-9)


def _unavailable(c):
    if c.fines_cut is None:
        return "the runs keep every sieve class already (sim.fines_cut_mm is null)"
    if not scalped_materials(c):
        return f"no material's sieve reaches below the fines cut ({1e3 * c.fines_cut:g} mm)"
    return None


MECHANISM = Mechanism(
    name="fines_kept",
    description="the fines below the scalping cut kept as sieved (share of their mass)",
    parameters=lambda c: {f"fines_kept_{m}": (LOW, HIGH) for m in scalped_materials(c)},
    available=_unavailable,
    null=lambda c: {f"fines_kept_{m}": LOW for m in scalped_materials(c)},
)
