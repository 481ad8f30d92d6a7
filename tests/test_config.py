"""conf/ composes into valid typed objects, the shipped YAML matches the paper's data, and bad
config values fail with the key path, the value and the allowed range."""
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from torchdem import config
from torchdem.cli import CONF_DIR
from torchdem.errors import ConfigError
from torchdem.measured import load_materials
from torchdem.mixture import pellet_sinter_mixture, sieve_from_table


def _compose(*overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="simulate", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


@pytest.mark.parametrize("name, pellet, layering", [
    ("pellet_sinter_50_50", 0.5, ("pellet", "sinter", "pellet", "sinter")),
    ("pellet_sinter_75_25", 0.75, ("pellet", "sinter", "pellet", "sinter")),
    ("pellet_sinter_25_75", 0.25, ("pellet", "sinter", "pellet", "sinter")),
    ("pellet_sinter_50_50_reverse", 0.5, ("sinter", "pellet", "sinter", "pellet")),
])
def test_paper_mixtures_compose_and_equal_the_python_api(name, pellet, layering):
    cfg = _compose(f"mixture={name}")
    mix = config.mixture_from(cfg["mixture"])
    assert mix.name == name and mix.layering == layering and mix.total_mass == 40.0
    assert dict(zip([m.name for m in mix.materials], mix.mass_fractions)) == {"pellet": pellet, "sinter": 1 - pellet}
    # the YAML files and the shipped data file (Tables 1 and 3) say the same
    api = pellet_sinter_mixture(pellet, reverse=layering[0] == "sinter")
    assert api.materials == mix.materials and api.layering == mix.layering


def test_material_yaml_matches_table_1():
    data = load_materials()
    mix = config.mixture_from(_compose()["mixture"])
    for m in mix.materials:
        assert m.sieve == sieve_from_table(data[m.name]["sieve_size_distribution"])
        assert m.density == data[m.name]["solid_density_kg_m3"]["mean"]


def test_three_material_user_mixture():
    mix = config.mixture_from(_compose("mixture=example_three_materials")["mixture"])
    assert [m.name for m in mix.materials] == ["pellet", "sinter", "lump_ore"]
    assert mix.layering == ("pellet", "lump_ore", "sinter", "pellet", "sinter")
    # masses per layer: each material's mass split equally over its layers
    layers = mix.layer_masses()
    assert [round(m, 9) for _, m in layers] == [6.0, 6.0, 6.0, 6.0, 6.0]


def test_geometry_groups():
    full = config.geometry_from(_compose("geometry=drawdown_full")["geometry"])
    slc = config.geometry_from(_compose("geometry=drawdown_slice")["geometry"])
    assert full.slice_depth is None and slc.slice_depth == 0.04
    assert slc.depth_scale == pytest.approx(0.2) and full.depth_scale == 1.0
    assert (full.upper_width, full.outlet_width) == (slc.upper_width, slc.outlet_width)


def test_cpu_and_gpu_profiles():
    cpu = config.run_settings_from(*(lambda c: (c["sim"], c["run"]))(_compose()))
    assert cpu.shear_modulus == 1e6 and cpu.fines_cut == pytest.approx(0.010)
    gpu_cfg = _compose("sim=gpu")
    gpu = config.run_settings_from(gpu_cfg["sim"], gpu_cfg["run"])
    assert gpu.shear_modulus is None and gpu.fines_cut is None and gpu.time_step_fraction == 0.15
    assert gpu.dtype == "float32" and gpu.compile


@pytest.mark.parametrize("override, words", [
    ("mixture.mass_fractions.pellet=1.5", ["mixture.mass_fractions", "pellet", "1.5", "[0.0, 1.0]"]),
    ("geometry.outlet_width_m=0.5", ["outlet_width", "0.5", "upper_width"]),
    ("geometry.slice_depth_m=-0.01", ["slice_depth_m", "-0.01", "> 0 m"]),
    ("sim.fines_cut_mm=-3", ["fines_cut_mm", "-3", "> 0 mm"]),
    ("sim.time_step_fraction=1.5", ["time_step_fraction", "1.5", "Rayleigh"]),
    ("run.discharge_time_s=1.0", ["discharge_time", "1.0", ">= 2.5"]),
    ("run.flow_window_s=[2.0,0.5]", ["flow_window", "(2.0, 0.5)", "start < end"]),
    ("mixture.materials.sinter.sieve.0.d_max_mm=1.0", ["mixture.materials.sinter.sieve[0]", "d_max_mm", "1.0"]),
    ("mixture.layering=[pellet,coke]", ["layering[1]", "coke"]),
    ("mixture.materials.pellet.shape=cube", ["mixture.materials.pellet", "cube", "sphere"]),
])
def test_bad_config_values_name_key_value_and_range(override, words):
    cfg = _compose(override)
    with pytest.raises(ConfigError) as err:
        config.mixture_from(cfg["mixture"])
        config.geometry_from(cfg["geometry"])
        config.run_settings_from(cfg["sim"], cfg["run"])
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_bad_contact_parameter_is_named_by_its_config_key():
    with pytest.raises(ConfigError, match=r"contact\.mu_s_pp = -0\.2 .*>= 0"):
        config.contact_from(_compose("contact.mu_s_pp=-0.2")["contact"])
    with pytest.raises(ConfigError, match=r"contact\.e_ss = 1\.5 .*\(0, 1\]"):
        config.contact_from(_compose("contact.e_ss=1.5")["contact"])


def test_bad_contact_parameter_is_named_when_the_table_is_built():
    from torchdem.drawdown import DrawDownTest, RunSettings
    from torchdem.geometry import DrawDownGeometry

    contact = {**config.contact_from(_compose()["contact"]), "mu_s_pp": -0.2}
    with pytest.raises(ConfigError, match="-0.2"):  # up front, before any particle is placed
        DrawDownTest(pellet_sinter_mixture(), DrawDownGeometry(slice_depth=0.04), contact,
                     RunSettings(shear_modulus=1e6))
