"""Named contact parameters: the paper's naming, the averaging rule for pellet-sinter,
explicit cross-pair values, per-member lists and clear errors."""
import pytest

from torchdem.contact_params import PAPER_REFERENCE, interaction_pairs
from torchdem.errors import ConfigError


def test_paper_reference_gives_all_pairs_with_averaged_cross_pair():
    pairs = interaction_pairs(PAPER_REFERENCE, ["pellet", "sinter"], "geometry")
    assert set(pairs) == {("pellet", "pellet"), ("pellet", "sinter"), ("pellet", "geometry"),
                          ("sinter", "sinter"), ("sinter", "geometry")}
    ps = pairs[("pellet", "sinter")]
    assert ps["mu_s"] == pytest.approx((0.49 + 0.7) / 2)
    assert ps["mu_r"] == pytest.approx((0.06 + 0.08) / 2)
    assert ps["restitution"] == pytest.approx((0.7 + 0.35) / 2)
    assert pairs[("sinter", "geometry")]["restitution"] == 0.4


def test_explicit_cross_pair_and_member_lists():
    params = dict(PAPER_REFERENCE, mu_s_pp=[0.4, 0.6], mu_s_ps=0.9)
    pairs = interaction_pairs(params, ["pellet", "sinter"], "geometry")
    assert pairs[("pellet", "sinter")]["mu_s"] == 0.9
    assert pairs[("pellet", "pellet")]["mu_s"] == [0.4, 0.6]
    params = dict(PAPER_REFERENCE, mu_s_pp=[0.4, 0.6])
    assert interaction_pairs(params, ["pellet", "sinter"], "geometry")[("pellet", "sinter")]["mu_s"] == \
        pytest.approx([0.55, 0.65])


def test_missing_and_malformed_names_are_reported():
    params = {k: v for k, v in PAPER_REFERENCE.items() if k != "e_sg"}
    with pytest.raises(ConfigError, match=r"missing e_sg \(pair sinter-geometry\)"):
        interaction_pairs(params, ["pellet", "sinter"], "geometry")
    with pytest.raises(ConfigError, match=r"'mu_x_pp'"):
        interaction_pairs(dict(PAPER_REFERENCE, mu_x_pp=0.1), ["pellet", "sinter"], "geometry")
    with pytest.raises(ConfigError, match=r"unknown material letter"):
        interaction_pairs(dict(PAPER_REFERENCE, mu_s_pq=0.1), ["pellet", "sinter"], "geometry")
