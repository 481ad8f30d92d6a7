"""Every command as a user runs it (tests/test_commands.py):

- bad input ends every entry point with one line, ``torchdem-<cmd>: error: <message>``, on
  stderr and exit status 2, before any progress bar or DEM work; the message names the config
  key the user typed, the value and the allowed range; ``HYDRA_FULL_ERROR=1`` gives the traceback;
- every command runs end to end on the mini box with every model extension of
  ``conf/extension/`` (the command x extension matrix, one Hydra multirun per command), with a
  procedure cut to a fraction of a second of simulated time so that each run takes seconds;
- each extension changes the model it names (the matrix alone would pass a silently ignored one).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
EXTENSIONS = sorted(p.stem for p in (REPO / "conf" / "extension").glob("*.yaml"))
#: Extensions that reach the model the way another one does, which the two campaign commands (the
#: matrix's costliest rows, 12-18 s a job) leave to it: clump_shape's trilobe as clump_size's,
#: free_interaction's and geometry_friction's contact parameters as cohesion's. Every extension still
#: changes the model (the test above) and runs with simulate, screen and study.
SAME_ROUTE = {"clump_shape": "clump_size", "free_interaction": "cohesion", "geometry_friction": "cohesion"}
#: Overrides an extension needs to apply to the mini box: fines_kept keeps the fines below the cut, and the
#: mini box's sieves have one class each, so its sinter gets a finer class and the cut above it.
NEEDS = {"fines_kept": ["mixture.materials.sinter.sieve=[{d_min_mm:10.0,d_max_mm:14.0,mass_fraction:0.3},"
                        "{d_min_mm:14.0,d_max_mm:18.0,mass_fraction:0.7}]", "sim.fines_cut_mm=12"]}
#: What each command writes when it has run end to end.
WRITTEN = {"simulate": "kpis.json", "screen": "screening.json", "study": "timestep.json",
           "calibrate": "calibration.json", "discover": "discovery.json"}
MODULES = {"demo": "torchdem.cli", "simulate": "torchdem.cli_simulate", "screen": "bo.cli.screen",
           "study": "bo.cli.study", "calibrate": "bo.cli.calibrate", "discover": "bo.cli.discover"}

# A fraction of a second of fill and discharge: enough for every stage to run, not to measure.
# Few bodies are at rest after it, so the photo's angle of repose is often missing: the campaign
# commands below use the KPIs such runs do measure (shear angle, lower-box mass). The loose fill
# at 0.2 fits its slabs at the first try: at 0.3 the mini box's placement retried crowded slabs
# and took a third of each command's time.
TINY_RUN = ["+experiment=mini", "run.fill_time_s=0.1", "run.discharge_time_s=0.3", "run.flow_window_s=[0.02,0.15]",
            "run.final_window_s=0.05", "run.loose_fraction=0.2"]
TINY = {
    "simulate": ["output.images=false", "output.progress=false"],
    "screen": ["screen=mini", "replicates=1"],
    "study": ["fractions=[0.2,0.3]", "replicates=2"],
    "calibrate": ["profile=smoke", "replicates=1", "surrogate.replicates=1", "surrogate.points_per_parameter=3",
                  "surrogate.budget=6", "ga.pop_size=20", "ga.n_generations=10", "ga.repetitions=1",
                  "verification.replicates=1", "objective.kpis=[shear_angle_deg,mass_lower_box_full_kg]"],
    "discover": ["profile=smoke", "discovery.conditions=[50-50,25-75]", "discovery.candidates=[density_per_material]",
                 "discovery.always_score=true", "discovery.replicates=2", "discovery.fit_replicates=1",
                 "discovery.points_per_parameter=3",
                 "discovery.ga={pop_size: 20, n_generations: 10, stall_generations: 5}",
                 "discovery.kpis=[shear_angle_deg,mass_lower_box_full_kg]"],
}


def run_command(command: str, *overrides: str, out: Path, env: dict | None = None, timeout: float = 600,
                multirun: bool = False):
    """``python -m <module of torchdem-<command>> overrides... hydra.run.dir=out``; with
    ``multirun``, ``-m`` and job k in ``out/k``."""
    where = ([f"hydra.sweep.dir={out}", "hydra.sweep.subdir=${hydra.job.num}"] if multirun
             else [f"hydra.run.dir={out}"])
    return subprocess.run([sys.executable, "-m", MODULES[command], *(["-m"] if multirun else []), *overrides, *where],
                          cwd=REPO, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})})


# ---------------------------------------------------------------------------------------------
# one-line errors
# ---------------------------------------------------------------------------------------------

BAD = [  # (command, override, what the message must name)
    ("simulate", "contact.mu_s_pp=-0.3", "contact.mu_s_pp = -0.3"),
    ("screen", "contact.mu_s_pp=-0.3", "contact.mu_s_pp = -0.3"),
    ("study", "contact.e_ss=1.5", "contact.e_ss = 1.5"),
    ("calibrate", "contact.mu_r_ss=-1", "contact.mu_r_ss = -1"),
    ("discover", "contact.mu_s_pp=-0.3", "contact.mu_s_pp = -0.3"),
    ("demo", "contact.mu_s=-0.3", "contact.mu_s = -0.3"),
    ("simulate", "sim.device=bogus", "sim.device"),
    ("simulate", "extension=cohesion extension.values.coh_pp=-5", "extension.values.coh_pp = -5"),
    ("calibrate", "measured=/nonexistent/lab.json", "/nonexistent/lab.json"),
    ("discover", "calibration=/nonexistent/calibration.json", "/nonexistent/calibration.json"),
]


@pytest.mark.parametrize("command, override, named", BAD, ids=[f"{c}:{o}" for c, o, _ in BAD])
def test_bad_input_is_one_line_and_exit_status_2(tmp_path, command, override, named):
    mini = [] if command == "demo" else TINY_RUN[:1]
    proc = run_command(command, *mini, *override.split(), out=tmp_path / "out", timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"torchdem-{command}: error: "), lines[0]
    assert named in lines[0]
    assert "Traceback" not in proc.stderr and "simulated s" not in proc.stderr  # no progress bar started
    assert not (tmp_path / "out" / "campaign.sqlite").exists()  # no store opened


@pytest.mark.parametrize("script", ["campaign_status.py", "stage_kpis.py", "residue_check.py"])
def test_a_script_given_what_is_not_a_store_ends_with_one_line(tmp_path, script):
    """The scripts end bad input as the commands do (``torchdem.errors.exit_on_bad_input``): one line,
    ``<script>: error: <message>`` naming the file, and exit status 2, not a traceback."""
    notes = tmp_path / "notes.sqlite"
    notes.write_text("lab notes, not a campaign store\n")
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / script), str(notes)], capture_output=True,
                          text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{script}: error: {notes}: not a campaign store"), proc.stderr


def test_range_message_states_the_allowed_range(tmp_path):
    proc = run_command("simulate", "+experiment=mini", "contact.e_ss=1.5", out=tmp_path / "out", timeout=120)
    assert proc.returncode == 2
    assert "expected a restitution coefficient in (0, 1]" in proc.stderr


def test_hydra_full_error_keeps_the_traceback(tmp_path):
    proc = run_command("simulate", "+experiment=mini", "contact.mu_s_pp=-0.3", out=tmp_path / "out",
                       env={"HYDRA_FULL_ERROR": "1"}, timeout=120)
    assert proc.returncode != 0
    assert "Traceback" in proc.stderr and "ConfigError" in proc.stderr


# ---------------------------------------------------------------------------------------------
# each extension changes the model it names
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("extension", [e for e in EXTENSIONS if e != "none"])
def test_extension_reaches_the_model(extension):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from bo.cli.common import model_from
    from torchdem import config

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        needs = NEEDS.get(extension, [])
        plain = OmegaConf.to_container(compose(config_name="screen", overrides=["+experiment=mini", *needs,
                                                                                 f"extension={extension}"]),
                                       resolve=True)
        base = OmegaConf.to_container(compose(config_name="screen", overrides=["+experiment=mini", *needs]),
                                      resolve=True)
    name, values = config.extension_from(plain["extension"])
    model, plain_model = model_from(plain), model_from(base)
    assert name == extension and values
    for key, value in values.items():
        assert model.fixed[key] == pytest.approx(value)
    test, plain_test = model.test_for(plain["condition"], [{}]), plain_model.test_for(base["condition"], [{}])
    mixture = test.member_mixtures[0] if test.member_mixtures else test.mixture
    changed = {
        "clump_shape": lambda: {m.shape for m in mixture.materials if m.name == "sinter"} == {"trilobe_s0.1500"},
        "clump_size": lambda: {m.shape for m in mixture.materials if m.name == "sinter"} == {"trilobe_s0.1500_k1.1600"},
        "cohesion": lambda: test.parameter_sets[0]["coh_pp"] == values["coh_pp"],
        "density_per_material": lambda: [m.density for m in mixture.materials] == [values["density_pellet"],
                                                                                   values["density_sinter"]],
        "fill_friction": lambda: test._fill_friction([0]) == [values["fill_friction"]] != plain_test._fill_friction([0]),
        "fines_kept": lambda: (min(c.d_min for m in mixture.materials for c in m.sieve)
                               < min(c.d_min for m in plain_test.mixture.materials for c in m.sieve)),
        "free_interaction": lambda: test.parameter_sets[0]["mu_s_ps"] == values["mu_s_ps"],
        "geometry_friction": lambda: ([test.parameter_sets[0][k] for k in ("mu_s_pg", "mu_s_sg")]
                                      == [values["mu_s_pg"], values["mu_s_sg"]]
                                      != [plain_test.parameter_sets[0][k] for k in ("mu_s_pg", "mu_s_sg")]),
        "front_back_walls": lambda: (test.settings.front_back_material is not None
                                     and plain_test.settings.front_back_material is None),
        "outlet_width": lambda: (test.geometry.outlet_width == values["geometry_outlet_width"]
                                 != plain_test.geometry.outlet_width),
        "rolling_ai2011": lambda: (test.settings.rolling_stiffness == "ai2011"
                                   and plain_test.settings.rolling_stiffness != "ai2011"),
    }
    assert changed[extension](), f"extension={extension} did not change the model"


# ---------------------------------------------------------------------------------------------
# the command x extension matrix
# ---------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("command", ["simulate", "screen", "study", "calibrate", "discover"])
def test_every_command_runs_with_every_extension(tmp_path, command):
    """One Hydra multirun per command sweeps every extension (``-m extension=a,b,...``), as a
    user sweeps them: each job runs end to end in its own directory and records its extension
    (calibrate and discover leave out the extensions of ``SAME_ROUTE``).
    One process per command instead of one per pair: the suite took 17.5 min instead of 18.3."""
    out = tmp_path / "sweep"
    extensions = [e for e in EXTENSIONS if (command not in ("calibrate", "discover") or e not in SAME_ROUTE)
                  and e not in NEEDS]
    assert set(SAME_ROUTE.values()) <= set(extensions) and set(SAME_ROUTE) <= set(EXTENSIONS)
    proc = run_command(command, *TINY_RUN, *TINY[command], f"extension={','.join(extensions)}", out=out,
                       timeout=1800, multirun=True)
    assert proc.returncode == 0, f"torchdem-{command} -m extension=...:\n{proc.stdout[-1500:]}\n{proc.stderr[-3000:]}"
    written = WRITTEN[command]
    for job, extension in enumerate(extensions):
        assert json.loads((out / str(job) / written).read_text()), (command, extension)
        saved = (out / str(job) / ".hydra" / "config.yaml").read_text()
        assert f"name: {extension}" in saved or (extension == "none" and "name: null" in saved), (command, extension)


@pytest.mark.slow
@pytest.mark.parametrize("extension", sorted(NEEDS))
def test_an_extension_with_needs_runs_with_every_command(tmp_path, extension):
    """The extensions left out of the matrix (they need a mini box with something to act on, NEEDS) run
    end to end with every command, with those needs."""
    for command in WRITTEN:
        out = tmp_path / command
        proc = run_command(command, *TINY_RUN, *TINY[command], *NEEDS[extension], f"extension={extension}", out=out,
                           timeout=900)
        assert proc.returncode == 0, f"torchdem-{command} extension={extension}:\n{proc.stderr[-3000:]}"
        assert json.loads((out / WRITTEN[command]).read_text()), (command, extension)
