"""Interaction parameters between unlike particle materials free, instead of the average of the
pure-material ones (the paper's rule, section 3.2.3). Prior: 0.5-1.5x the average of the pure
pairs' calibrated sliding and rolling friction; restitution 0.2-0.95."""
from itertools import combinations

from torchdem.mechanisms import Mechanism


def _parameters(c):
    out = {}
    for a, b in combinations(c.materials, 2):
        la, lb = c.letters[a], c.letters[b]
        ab = "".join(sorted((la, lb)))
        for coeff in ("mu_s", "mu_r"):
            avg = 0.5 * (c.calibrated[f"{coeff}_{la}{la}"] + c.calibrated[f"{coeff}_{lb}{lb}"])
            out[f"{coeff}_{ab}"] = (0.5 * avg, 1.5 * avg)
        out[f"e_{ab}"] = (0.2, 0.95)
    return out


def _null(c):
    """The averaging rule itself (the restitution average only where both pure values are known)."""
    out = {}
    for a, b in combinations(c.materials, 2):
        la, lb = c.letters[a], c.letters[b]
        ab = "".join(sorted((la, lb)))
        for coeff in ("mu_s", "mu_r", "e"):
            pure = [c.calibrated.get(f"{coeff}_{l}{l}") for l in (la, lb)]
            if None in pure:
                return None
            out[f"{coeff}_{ab}"] = 0.5 * (pure[0] + pure[1])
    return out


MECHANISM = Mechanism(
    name="free_interaction",
    description="unlike-material interaction parameters (mu_s, mu_r, e) free, not the pure pairs' average",
    parameters=_parameters,
    available=lambda c: None if len(c.materials) > 1 else "one particle material: no unlike pair",
    null=_null,
)
