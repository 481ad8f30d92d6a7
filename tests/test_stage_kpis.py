"""scripts/stage_kpis.py: a store's checking stages against the measured data, read while a campaign runs."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from bo.calibration.pipeline import agreement
from bo.campaign.executor import EvalOutcome
from bo.campaign.store import CampaignStore, copy_store
from torchdem.errors import ConfigError
from torchdem.measured import load_measured


def _script():
    spec = importlib.util.spec_from_file_location("stage_kpis", Path(__file__).resolve().parents[1]
                                                  / "scripts" / "stage_kpis.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module            # its dataclass looks its module up
    spec.loader.exec_module(module)
    return module


def _kpis(heap: float, face: float, flow: float, lower: float) -> dict[str, float]:
    """A reduced box's KPIs: the half box's masses beside the whole box's (``_full_``)."""
    return {"angle_of_repose_deg": heap, "shear_angle_deg": face, "mass_flow_rate_kg_s": flow / 2,
            "mass_flow_rate_full_kg_s": flow, "mass_lower_box_kg": lower / 2, "mass_lower_box_full_kg": lower}


def test_means_errors_and_ci_flags_of_each_stage_against_table_2(tmp_path, capsys):
    """Table 2's 50-50: heap 29.47 +- 0.48, face 42.51 +- 1.62, flow 10.29 +- 0.35, lower box 32.32 +- 0.55.
    Three verification runs of known KPIs (heap 29.2, 29.6, 30: mean 29.60, +0.4 %, inside; face 38, 38, 38:
    -10.6 %, outside; flow 10.29 exactly; lower box 32, 32.5, 33: 32.5, +0.6 %) and one that jammed (every KPI
    0), which must not enter the means. The whole box's masses stand for the lab's, the half box's never."""
    script = _script()
    measured = load_measured(None)
    store = CampaignStore(tmp_path / "own.sqlite", "cfg", code_version="test")
    store.batch("verification", "set/a", lambda: [{"mu_s_pp": 0.8}], seeds=[0, 1, 2, 3], conditions=["50-50"])
    tasks = store.claim(4, "verification")
    values = [_kpis(29.2, 38.0, 10.29, 32.0), _kpis(29.6, 38.0, 10.29, 32.5), _kpis(30.0, 38.0, 10.29, 33.0),
              {**_kpis(0.0, 0.0, 0.0, 0.0), "discharge_jammed": 1.0}]
    store.record([(t, EvalOutcome.success(v, 1.0)) for t, v in zip(tasks, values)])
    store.batch("screening", "design", lambda: [{"mu_s_pp": 0.6}], seeds=[0], conditions=["50-50"])
    store.record([(t, EvalOutcome.success(_kpis(1.0, 1.0, 1.0, 1.0), 1.0)) for t in store.claim(1, "screening")])

    (row,) = script.stage_kpis(store.path, measured)          # the screening is no checking stage
    assert (row.stage, row.condition, row.runs, row.jammed, row.copied_from) == (
        "verification", "50-50", 3, 1, None)
    assert set(row.means) == {"angle_of_repose_deg", "shear_angle_deg", "mass_flow_rate_full_kg_s",
                              "mass_lower_box_full_kg"}
    assert row.means["angle_of_repose_deg"] == pytest.approx(29.6)
    assert row.sds["angle_of_repose_deg"] == pytest.approx(0.4)
    assert row.means["mass_lower_box_full_kg"] == pytest.approx(32.5)

    script.main([str(store.path)])
    out = capsys.readouterr().out
    line = next(s for s in out.splitlines() if s.startswith("| 50-50"))
    assert line == ("| 50-50 | 3 | 1 | 29.60 (+0.4 %) | 38.00 (-10.6 %*) | 10.29 (+0.0 %) | 32.50 (+0.6 %) |")
    # 0.01 deg further out than the CI's half-width is outside it
    one = agreement(np.array([[29.96]]), ["angle_of_repose_deg"], measured.condition("50-50").kpis)
    assert script.format_stage_kpis([script.StageKPIs("verification", "set/c", "50-50", None, 1, one)]) \
        .splitlines()[-1] == "| 50-50 | 1 | 0 | 29.96 (+1.7 %*) |"
    assert "angle_of_repose_deg | shear_angle_deg | mass_flow_rate_full_kg_s | mass_lower_box_full_kg |" in out

    # a copy marks the batches it came with, and the copy's own runs apart
    copy = tmp_path / "copy.sqlite"
    copy_store(store.path, copy)
    copied = CampaignStore(copy, "cfg", code_version="test")
    copied.batch("validation", "set/b", lambda: [{"mu_s_pp": 0.7}], seeds=[0], conditions=["25-75"])
    copied.record([(t, EvalOutcome.success(_kpis(29.63, 44.76, 10.24, 32.0), 1.0))
                   for t in copied.claim(1, "validation")])
    rows = {r.stage: r for r in script.stage_kpis(copy, measured)}
    assert rows["verification"].copied_from == str(store.path)
    assert rows["validation"].copied_from is None
    script.main([str(copy), "--stages", "validation"])
    out = capsys.readouterr().out
    assert "## validation, batch set/b\n" in out and "verification" not in out
    assert "| 25-75 | 1 | 0 | 29.63 (+0.0 %) | 44.76 (+0.0 %) | 10.24 (+0.0 %) | 32.00 (+0.0 %) |" in out


def test_a_missing_store_is_named():
    with pytest.raises(ConfigError, match="nowhere.sqlite"):
        _script().main(["nowhere.sqlite"])
