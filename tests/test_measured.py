"""Tests for torchdem.measured: the shipped paper data, the file format and its errors.

The Table 2 numbers below are typed again from the paper (Hadi, Pang & Schott, Table 2), a
second transcription independent of the shipped JSON file.
"""
from __future__ import annotations

import json
import math
import pathlib
import re

import pytest

from torchdem.errors import ConfigError
from torchdem.measured import (
    CALIBRATION_KPIS,
    KPI_UNITS,
    PAPER_KPIS,
    Condition,
    KPIValue,
    MeasuredData,
    MeasuredDataError,
    UnknownConditionError,
    load_materials,
    load_measured,
    load_paper_tables,
)

# Table 2: condition -> (AoR deg, shear angle deg, mass flow kg/s, mass lower box kg,
# RSD vertical, RSD horizontal), each (mean, 95 % CI half-width).
TABLE_2 = {
    "50-50": ((29.47, 0.48), (42.51, 1.62), (10.29, 0.35), (32.32, 0.55), (0.264, 0.07), (0.121, 0.04)),
    "75-25": ((28.55, 0.65), (39.03, 1.49), (10.29, 0.10), (33.09, 0.12), (0.151, 0.03), (0.082, 0.02)),
    "25-75": ((29.63, 0.75), (44.76, 1.21), (10.24, 0.45), (32.00, 0.48), (0.422, 0.09), (0.116, 0.025)),
    "50-50-reverse": ((29.74, 0.47), (40.92, 1.55), (10.39, 0.56), (32.97, 0.20), (0.320, 0.03), (0.112, 0.053)),
}
PELLET_FRACTION = {"50-50": 0.5, "75-25": 0.75, "25-75": 0.25, "50-50-reverse": 0.5}
NORMAL = ("pellet", "sinter", "pellet", "sinter")
REVERSE = ("sinter", "pellet", "sinter", "pellet")
UNITS = {"angle_of_repose_deg": "deg", "shear_angle_deg": "deg", "mass_flow_rate_kg_s": "kg/s",
         "mass_lower_box_kg": "kg", "segregation_rsd_vertical": "1", "segregation_rsd_horizontal": "1"}


@pytest.fixture(scope="module")
def shipped() -> MeasuredData:
    return load_measured(required_kpis=PAPER_KPIS)


@pytest.fixture
def shipped_dict() -> dict:
    # The raw shipped file, as a starting point for malformed variants.
    return json.loads(pathlib.Path(load_measured().origin).read_text(encoding="utf-8"))


def write(tmp_path: pathlib.Path, data: dict, name: str = "lab.json") -> pathlib.Path:
    path = tmp_path / name
    path.write_text(json.dumps(data), encoding="utf-8")
    return path


# ------------------------------------------------------------------------ shipped data


def test_shipped_file_is_inside_the_package(shipped):
    origin = pathlib.Path(shipped.origin)
    assert origin.name == "hadi2025_pellet_sinter.json"
    assert origin.parent.name == "data" and origin.parent.parent.name == "torchdem"
    assert "/work/shared" not in str(origin)


def test_source_cites_the_paper_and_its_tables(shipped):
    assert "A. Hadi, Y. Pang, D. Schott" in shipped.source
    assert "Systematic DEM calibration of two-component mixtures using AI-accelerated surrogate models" \
        in shipped.source
    for table in ("Table 1", "Table 2", "Table 3", "A.4", "A.5", "A.6"):
        assert table in shipped.source


@pytest.mark.parametrize("name", list(TABLE_2))
def test_shipped_kpis_match_table_2(shipped, name):
    condition = shipped.condition(name)
    assert tuple(condition.kpis) == PAPER_KPIS
    for kpi, (mean, ci95) in zip(PAPER_KPIS, TABLE_2[name]):
        value = condition.kpis[kpi]
        assert value.mean == mean, (name, kpi)
        assert value.ci95 == ci95, (name, kpi)
        assert value.unit == UNITS[kpi]


def test_shipped_conditions_mixture_definition(shipped):
    assert shipped.names == ("50-50", "75-25", "25-75", "50-50-reverse")
    for name, fraction in PELLET_FRACTION.items():
        condition = shipped.condition(name)
        assert condition.pellet_mass_fraction == fraction
        assert condition.mass_fractions() == {"pellet": fraction, "sinter": 1.0 - fraction}
        assert condition.fill_mass_kg == 40.0
        assert condition.layering == (REVERSE if name == "50-50-reverse" else NORMAL)
        assert condition.mixture is None


def test_max_heap_height_is_not_invented(shipped):
    # The paper shows the heap height only in Fig. 15; no number may appear in the data.
    assert "max_heap_height_m" in KPI_UNITS
    assert all("max_heap_height_m" not in c.kpis for c in shipped.conditions)
    assert any("heap height" in note for note in shipped.notes)


def test_sieve_fractions_sum_to_one():
    materials = load_materials()
    for name in ("pellet", "sinter"):
        classes = materials[name]["sieve_size_distribution"]
        assert math.isclose(sum(c["mass_fraction"] for c in classes), 1.0, abs_tol=1e-3), name
        for lower, upper in zip(classes, classes[1:]):
            assert lower["d_max_mm"] == upper["d_min_mm"], name  # contiguous sieve classes
    sinter = {(c["d_min_mm"], c["d_max_mm"]): c["mass_fraction"]
              for c in materials["sinter"]["sieve_size_distribution"]}
    assert sinter == {(5.6, 8.0): 0.3637, (8.0, 10.0): 0.2313, (10.0, 12.5): 0.1761,
                      (12.5, 16.0): 0.1345, (16.0, 20.0): 0.0508, (20.0, 25.0): 0.0436}
    pellet = {(c["d_min_mm"], c["d_max_mm"]): c["mass_fraction"]
              for c in materials["pellet"]["sieve_size_distribution"]}
    assert pellet == {(10.0, 12.5): 0.48, (12.5, 16.0): 0.52}


def test_material_properties_tables_1_and_3():
    materials = load_materials()
    assert materials["pellet"]["solid_density_kg_m3"] == {"mean": 3602.4, "plus_minus": 61.7}
    assert materials["sinter"]["solid_density_kg_m3"] == {"mean": 3449.0, "plus_minus": 34.0}
    for name, shear_modulus, poisson in (("pellet", 1e8, 0.25), ("sinter", 1e8, 0.25), ("geometry", 2e11, 0.3)):
        assert materials[name]["shear_modulus_pa"] == shear_modulus
        assert materials[name]["poisson_ratio"] == poisson


# ------------------------------------------------------------------ DEM-reported tables


def test_dsd_levels_are_reference_plus_minus_25_percent():
    levels = load_paper_tables()["dsd_levels"]["levels"]
    assert len(levels) == 12
    for name, level in levels.items():
        # Table 4 prints the +-25 % levels rounded to 3 decimals.
        assert level["low"] == pytest.approx(0.75 * level["mid"], abs=6e-4), name
        assert level["high"] == pytest.approx(1.25 * level["mid"], abs=6e-4), name
    assert levels["mu_s_pp"] == {"low": 0.368, "mid": 0.49, "high": 0.613}
    assert levels["e_sg"] == {"low": 0.3, "mid": 0.4, "high": 0.5}


def test_extended_bounds_and_calibrated_sets_lie_inside_them():
    tables = load_paper_tables()
    bounds = tables["extended_bounds"]["bounds"]
    assert bounds["mu_r_pp"] == {"low": 0.075, "high": 0.24}
    assert set(bounds) == {"mu_s_pp", "mu_r_pp", "e_pp", "mu_s_ss", "mu_s_pg", "mu_r_pg", "mu_s_sg"}
    ga = tables["ga_calibration"]
    assert ga["restricted"] == {"mu_s_pp": 0.73, "mu_r_pp": 0.12, "e_pp": 0.76, "mu_s_ss": 0.9,
                                "mu_s_pg": 0.9, "mu_r_pg": 0.16, "mu_s_sg": 0.83}
    assert ga["unrestricted"] == {"mu_s_pp": 0.75, "mu_r_pp": 0.11, "e_pp": 0.76, "mu_s_ss": 0.91,
                                  "mu_s_pg": 1.0, "mu_r_pg": 0.17, "mu_s_sg": 0.79}
    assert max(ga["restricted"].values()) <= ga["restricted_upper_bound"]
    sets = [ga["restricted"], ga["unrestricted"], *tables["ga_repetitions"]["repetitions"]]
    for parameters in sets:
        for name, bound in bounds.items():
            assert bound["low"] <= parameters[name] <= bound["high"], name


def test_table_9_selected_repetition_has_lowest_fitness():
    table = load_paper_tables()["ga_repetitions"]
    repetitions = table["repetitions"]
    assert [r["repetition"] for r in repetitions] == list(range(1, 11))
    best = min(repetitions, key=lambda r: r["fitness"])
    assert best["repetition"] == table["selected_repetition"] == 4
    assert best == {"repetition": 4, "mu_s_pp": 0.74, "mu_r_pp": 0.12, "e_pp": 0.76, "mu_s_ss": 0.9,
                    "mu_s_pg": 0.9, "mu_r_pg": 0.16, "mu_s_sg": 0.83, "fitness": 0.5475}
    # Table 8's restricted column is repetition 1 of Table 9.
    first = {k: v for k, v in repetitions[0].items() if k not in ("repetition", "fitness")}
    assert first == load_paper_tables()["ga_calibration"]["restricted"]


def test_surrogate_ga_time_step_and_density():
    tables = load_paper_tables()
    r2 = tables["surrogate_r2"]["iterations"]
    assert [(i["n_points"], i["r2_mean"]) for i in r2] == [
        (70, 0.84), (80, 0.88), (90, 0.92), (100, 0.93), (110, 0.95)]
    assert tables["ga_settings"] | {"table": None} == {
        "table": None, "population_size": 1000, "max_generations": 2000, "crossover_probability": 0.6,
        "mutation_probability": 0.05, "function_tolerance": 1e-6}
    assert tables["time_step"]["fraction_of_rayleigh"] == 0.15
    assert tables["time_step"]["time_step_s"] == 5.91e-6
    recalibration = tables["bulk_density_recalibration"]
    assert recalibration["heap_height_ratio_dem_over_exp"] == 0.93
    assert recalibration["particle_density_kg_m3"] == {"pellet": 3350.0, "sinter": 3208.0}
    # Section 3.6: the new densities are the measured ones (Table 1) times 0.93, to 1 kg/m3.
    materials = load_materials()
    for name in ("pellet", "sinter"):
        measured = materials[name]["solid_density_kg_m3"]["mean"]
        assert recalibration["particle_density_kg_m3"][name] == pytest.approx(0.93 * measured, abs=0.5)


def _appendix_rows():
    tables = load_paper_tables()["dem_vs_experiment"]
    yield "50-50", tables["calibration"]
    yield "50-50", tables["calibration_recalibrated_density"]
    yield from tables["validation"]["conditions"].items()


def test_appendix_experiment_rows_equal_table_2(shipped):
    rows = list(_appendix_rows())
    assert [name for name, _ in rows] == ["50-50", "50-50", "75-25", "25-75", "50-50-reverse"]
    for name, row in rows:
        for kpi in CALIBRATION_KPIS:
            value = shipped.condition(name).kpis[kpi]
            assert row["experiments"][kpi] == {"mean": value.mean, "ci95": value.ci95}, (name, kpi)


def test_appendix_relative_errors_agree_with_means_within_rounding():
    # RE = 100 (y_DEM - y_exp) / y_exp from means printed to 2 decimals: each mean may be off
    # by 0.005 and the printed RE by 0.005, which bounds the disagreement.
    for name, row in _appendix_rows():
        for kpi in CALIBRATION_KPIS:
            exp, dem = row["experiments"][kpi]["mean"], row["dem"][kpi]["mean"]
            recomputed = 100.0 * (dem - exp) / exp
            bound = 100.0 * 0.005 * (1.0 + abs(dem / exp)) / exp + 0.005
            assert abs(recomputed - row["relative_error_percent"][kpi]) <= bound, (name, kpi)


# ------------------------------------------------------------------ format and API


def test_round_trip_save_load(shipped, tmp_path):
    path = tmp_path / "copy.json"
    shipped.save(path)
    again = load_measured(path)
    assert again == shipped
    assert again.to_dict() == shipped.to_dict()
    assert again.origin == str(path)


def test_user_file_with_kpi_subset_new_kpi_and_three_materials(shipped, tmp_path):
    extra = Condition(
        name="coke-mix", pellet_mass_fraction=None, layering=("coke", "pellet", "sinter"),
        fill_mass_kg=30.0,
        kpis={"angle_of_repose_deg": KPIValue(31.0, 0.5, "deg"),
              "discharge_time_s": KPIValue(4.2, 0.3, "s")},
        mixture={"materials": [{"name": "pellet", "mass_fraction": 0.4},
                               {"name": "sinter", "mass_fraction": 0.4},
                               {"name": "coke", "mass_fraction": 0.2, "bulk_density_kg_m3": 550.0}],
                 "layering": ["coke", "pellet", "sinter"]},
        description="lab test, three materials")
    subset = Condition(name="80-20", pellet_mass_fraction=0.8, layering=NORMAL, fill_mass_kg=None,
                       kpis={"shear_angle_deg": KPIValue(38.0, 1.0, "deg")})
    data = shipped.with_condition(extra).with_condition(subset)
    assert data.names[-2:] == ("coke-mix", "80-20")
    path = tmp_path / "lab.json"
    data.save(path)
    written = json.loads(path.read_text(encoding="utf-8"))
    assert written["units"]["discharge_time_s"] == "s"
    again = load_measured(path)
    assert again == data
    assert again.condition("coke-mix").mass_fractions() == {"pellet": 0.4, "sinter": 0.4, "coke": 0.2}
    assert again.condition("coke-mix").mixture["materials"][2]["bulk_density_kg_m3"] == 550.0
    assert again.condition("80-20").fill_mass_kg is None
    with pytest.raises(MeasuredDataError, match=r'conditions\["80-20"\]\.kpis\.angle_of_repose_deg is missing'):
        load_measured(path, required_kpis=CALIBRATION_KPIS)


def test_subset_keeps_the_named_conditions_in_their_order(shipped):
    sub = shipped.subset(["25-75", "50-50"])
    assert sub.names == ("25-75", "50-50") and sub.origin == shipped.origin
    assert sub.condition("50-50") == shipped.condition("50-50")
    for bad in ([], ["50-50", "50-50"], ["50/50"]):
        with pytest.raises(ConfigError, match=r"lab: conditions = .* is not allowed; expected a non-empty list of "
                                              r"distinct conditions of .*hadi2025_pellet_sinter.json: \['50-50'"):
            shipped.subset(bad, "lab")


def test_unknown_condition_lists_known_names(shipped):
    with pytest.raises(UnknownConditionError) as error:
        shipped.condition("50/50")
    message = str(error.value)
    assert "hadi2025_pellet_sinter.json" in message
    for name in TABLE_2:
        assert name in message
    assert "did you mean '50-50'" in message
    assert isinstance(error.value, KeyError)


# ------------------------------------------------------------------ malformed files


def _break(data: dict, mutate) -> dict:
    mutate(data)
    return data


MALFORMED = {
    "missing ci95": (lambda d: d["conditions"]["75-25"]["kpis"]["shear_angle_deg"].pop("ci95"),
                     r'conditions\["75-25"\]\.kpis\.shear_angle_deg\.ci95 is missing'),
    "missing kpis": (lambda d: d["conditions"]["25-75"].pop("kpis"),
                     r'conditions\["25-75"\]\.kpis is missing'),
    "missing source": (lambda d: d.pop("source"), r"source is missing"),
    "missing layering": (lambda d: d["conditions"]["50-50"].pop("layering"),
                         r'conditions\["50-50"\]\.layering is missing'),
    "NaN mean": (lambda d: d["conditions"]["50-50"]["kpis"]["mass_flow_rate_kg_s"].update(mean=float("nan")),
                 r'conditions\["50-50"\]\.kpis\.mass_flow_rate_kg_s\.mean = nan is not allowed'),
    "negative CI": (lambda d: d["conditions"]["50-50-reverse"]["kpis"]["angle_of_repose_deg"].update(ci95=-0.47),
                    r'conditions\["50-50-reverse"\]\.kpis\.angle_of_repose_deg\.ci95 = -0\.47 is not allowed'),
    "non-numeric": (lambda d: d["conditions"]["50-50"]["kpis"]["mass_lower_box_kg"].update(mean="32.32"),
                    r"mass_lower_box_kg\.mean = '32\.32' is not allowed; expected a finite number"),
    "boolean": (lambda d: d["conditions"]["50-50"]["kpis"]["mass_lower_box_kg"].update(ci95=True),
                r"mass_lower_box_kg\.ci95 = True is not allowed"),
    "KPI name typo": (lambda d: d["conditions"]["50-50"]["kpis"].update(
        angle_of_repose_dg=d["conditions"]["50-50"]["kpis"].pop("angle_of_repose_deg")),
        r"kpis\.angle_of_repose_dg is not a known KPI; did you mean 'angle_of_repose_deg'\?"),
    "KPI field typo": (lambda d: d["conditions"]["50-50"]["kpis"]["shear_angle_deg"].update(ci=1.0),
                       r"shear_angle_deg\.ci is not a known key; allowed: mean, ci95"),
    "condition key typo": (lambda d: d["conditions"]["50-50"].update(
        pellet_mass_fration=d["conditions"]["50-50"].pop("pellet_mass_fraction")),
        r"pellet_mass_fration is not a known key.*did you mean 'pellet_mass_fraction'\?"),
    "angle out of range": (lambda d: d["conditions"]["75-25"]["kpis"]["shear_angle_deg"].update(mean=139.03),
                           r"shear_angle_deg\.mean = 139\.03 is not allowed; expected a finite number in \[0, 90\]"),
    "wrong unit": (lambda d: d["units"].update(mass_flow_rate_kg_s="kg/min"),
                   r"units\.mass_flow_rate_kg_s = 'kg/min' is not allowed; expected 'kg/s'"),
    "unknown layer": (lambda d: d["conditions"]["50-50"]["layering"].__setitem__(2, "coke"),
                      r'conditions\["50-50"\]\.layering\[2\] = \'coke\' is not allowed'),
    "mass fraction above 1": (lambda d: d["conditions"]["75-25"].update(pellet_mass_fraction=75),
                              r'conditions\["75-25"\]\.pellet_mass_fraction = 75 is not allowed; '
                              r'expected a mass fraction in \[0, 1\]'),
    "unknown top-level key": (lambda d: d.update(conditons={}), r"conditons is not a known key"),
    "more in the lower box than filled": (
        lambda d: d["conditions"]["50-50"]["kpis"]["mass_lower_box_kg"].update(mean=323.2),
        r'conditions\["50-50"\]\.kpis\.mass_lower_box_kg\.mean = 323\.2 is not allowed; expected at most the mass '
        r'filled, fill_mass_kg = 40 kg'),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_file_names_file_and_key(shipped_dict, tmp_path, case):
    mutate, pattern = MALFORMED[case]
    path = write(tmp_path, _break(shipped_dict, mutate), name="broken_measured.json")
    with pytest.raises(MeasuredDataError, match=pattern) as error:
        load_measured(path)
    assert str(error.value).startswith(f"{path}: ")
    assert isinstance(error.value, ConfigError)


def test_mixture_fractions_must_sum_to_one(tmp_path):
    data = {"source": "lab notebook 7",
            "conditions": {"three": {"mixture": {"materials": [{"name": "a", "mass_fraction": 0.5},
                                                               {"name": "b", "mass_fraction": 0.3}],
                                                 "layering": ["a", "b"]},
                                     "kpis": {"angle_of_repose_deg": {"mean": 30.0, "ci95": 0.5}}}}}
    path = write(tmp_path, data)
    with pytest.raises(MeasuredDataError, match=r'lab\.json: conditions\["three"\]\.mixture\.materials\[\*\]'
                                                r'\.mass_fraction \(sum\) = 0\.8 is not allowed'):
        load_measured(path)


def test_duplicate_key_and_invalid_json_name_the_file(tmp_path):
    duplicate = tmp_path / "dup.json"
    duplicate.write_text('{"source": "x", "conditions": {"a": {}, "a": {}}}', encoding="utf-8")
    with pytest.raises(MeasuredDataError, match=re.escape(f"{duplicate}: 'a' appears twice")):
        load_measured(duplicate)
    broken = tmp_path / "broken.json"
    broken.write_text('{"source": "x",', encoding="utf-8")
    with pytest.raises(MeasuredDataError, match=re.escape(f"{broken}: line 1 column ") + r"\d+ is not valid JSON"):
        load_measured(broken)
    with pytest.raises(ConfigError, match="missing.json: cannot read"):
        load_measured(tmp_path / "missing.json")


def test_required_kpi_typo_is_reported():
    with pytest.raises(ConfigError, match="required_kpis: 'shear_angle' is not a known KPI"):
        load_measured(required_kpis=["shear_angle"])


def test_dataclasses_validate_when_built_in_code():
    with pytest.raises(MeasuredDataError, match=r"KPIValue: ci95 = -1\.0 is not allowed"):
        KPIValue(1.0, -1.0, "deg")
    with pytest.raises(MeasuredDataError, match="exactly one of 'pellet_mass_fraction'"):
        Condition("x", None, NORMAL, 40.0, {"shear_angle_deg": KPIValue(40.0, 1.0, "deg")})
    with pytest.raises(MeasuredDataError, match=r"kpis\.shear_angle_deg\.unit = 'rad' is not allowed"):
        Condition("x", 0.5, NORMAL, 40.0, {"shear_angle_deg": KPIValue(0.7, 0.01, "rad")})
    condition = Condition("x", 0.5, NORMAL, 40.0, {"shear_angle_deg": KPIValue(40.0, 1.0, "deg")})
    with pytest.raises(MeasuredDataError, match=r"MeasuredData: conditions = \['x'\] is not allowed; expected unique"):
        MeasuredData("notebook", (condition, condition))


def test_sieve_fractions_not_summing_to_one_name_file_and_key(shipped_dict, tmp_path):
    shipped_dict["materials"]["sinter"]["sieve_size_distribution"][0]["mass_fraction"] = 0.4637  # OCR-style slip
    path = write(tmp_path, shipped_dict)
    with pytest.raises(MeasuredDataError, match=re.escape(
            f"{path}: materials.sinter.sieve_size_distribution mass fractions sum to 1.100000")):
        load_materials(path)
    bare = write(tmp_path, {"source": "x", "conditions": {}}, name="no_materials.json")
    with pytest.raises(MeasuredDataError, match=re.escape(f"{bare}: materials is missing")):
        load_materials(bare)
