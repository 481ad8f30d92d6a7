"""``bo.calibration.document``: a calibration.json read back by the tools that start from a calibrated set, with
errors that name the option and the file, and without importing the surrogate stack."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from bo.calibration.document import calibrated_parameters, read_calibration
from torchdem.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "campaigns" / "table2" / "calibration_lab_priors.json"


def test_the_shipped_calibration_reads_as_its_calibrated_set_with_or_without_the_held_values():
    doc = json.loads(SHIPPED.read_text())
    values = calibrated_parameters(SHIPPED, "calibration")
    assert values == doc["calibrated_parameters"]
    whole = calibrated_parameters(SHIPPED, "--at", held=True)
    assert set(whole) == set(doc["calibrated_parameters"]) | set(doc["held_parameters"])
    assert whole["mu_r_pp"] == doc["held_parameters"]["mu_r_pp"]            # held, not calibrated
    assert whole["mu_r_ss"] == doc["calibrated_parameters"]["mu_r_ss"]
    assert read_calibration(SHIPPED, "calibration")["condition"] == "50-50"


@pytest.mark.parametrize("text, message", [
    (None, r"calibration = '.*missing.json': cannot read it"),
    ("{not json", r"calibration = '.*': not JSON \(.* at line 1\)"),
    ("[1, 2]", r"a JSON list, expected the object of a calibration.json"),
    ('{"condition": "50-50"}', r"no 'calibrated_parameters' object"),
    ('{"calibrated_parameters": {}}', r"no 'calibrated_parameters' object"),
    ('{"calibrated_parameters": {"mu_s_pp": "high"}}', r"calibrated_parameters.mu_s_pp = 'high' is not allowed; expected a finite number"),
    ('{"calibrated_parameters": {"mu_s_pp": NaN}}', r"calibrated_parameters.mu_s_pp = nan is not allowed; expected a finite number"),
    ('{"calibrated_parameters": {"mu_s_pp": 0.5}, "held_parameters": [0.1]}', r"no 'held_parameters' object"),
])
def test_a_bad_calibration_file_names_the_option_the_file_and_what_is_wrong(tmp_path, text, message):
    path = tmp_path / ("missing.json" if text is None else "calibration.json")
    if text is not None:
        path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        calibrated_parameters(path, "calibration", held=True)


def test_reading_a_calibration_does_not_import_the_surrogate_stack():
    code = ("import sys, bo.calibration.document as d; "
            "print(sorted(m for m in ('botorch', 'gpytorch', 'pymoo', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
