"""Strict JSON everywhere (issue 20, item 6): no NaN or Infinity in any JSON file or `--json` output.

The parser here is json.loads with ``parse_constant`` raising, so ``NaN``, ``Infinity`` and
``-Infinity`` (which Python's default parser accepts) fail the test. Two cases: `diagnose --json`
on imported data without time_s (the drift candidate printed bare NaN before), and every JSON file
a small plan → run → calibrate (with a tiny network) → diagnose writes."""

import csv
import json
import math
import os

import numpy as np
import pytest

from campaign.cli import main
from campaign.fileio import finite_json, strict_json


def strict_loads(text):
    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")
    return json.loads(text, parse_constant=refuse)


def test_the_strict_parser_refuses_what_python_writes_by_default():
    with pytest.raises(ValueError, match="NaN"):
        strict_loads(json.dumps({"a": float("nan")}))
    doc = {"a": float("nan"), "b": [1.0, float("inf")], "c": np.float32("-inf"), "d": np.arange(2.0)}
    out = strict_loads(strict_json(doc))
    assert out == {"a": None, "b": [1.0, None], "c": None, "d": [0.0, 1.0],
                   "null_reasons": {"a": "not a number (NaN): not computable from these data",
                                    "c": "-infinity: not computable from these data"}}
    assert finite_json({"x": 2.5, "y": True, "z": None}) == {"x": 2.5, "y": True, "z": None}


def test_diagnose_json_without_time_s_is_strict_and_says_why_drift_was_not_scored(tmp_path, capsys):
    src, run = tmp_path / "m.csv", tmp_path / "run"
    assert main(["synth", "--csv", str(src), "--poses", "40", "--seed", "9"]) == 0
    rows = list(csv.reader(src.open()))
    keep = [k for k, h in enumerate(rows[0]) if h != "time_s"]
    no_time = tmp_path / "no_time.csv"
    no_time.write_text("".join(",".join(r[k] for k in keep) + "\n" for r in rows))
    assert main(["import", str(no_time), "--run", str(run), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json", "--folds", "3", "--candidates", "drift,joint_compliance",
                 "--no-report"]) == 0
    out = strict_loads(capsys.readouterr().out)
    assert [c["effect"] for c in out["ranking"]] == ["joint_compliance"]
    assert out["skipped_candidates"] == [{"effect": "drift", "reason": "needs context time_s (time_s: not in the "
                                                                      "data for every pose)"}]
    assert strict_loads((run / "diagnose" / "diagnosis.json").read_text())["diagnosis_id"] == out["diagnosis_id"]


def test_every_json_file_of_a_small_end_to_end_run_is_strict(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["plan", "--run", str(run), "--grid-scale", "0.4", "--select", "40", "--quiet"]) == 0
    assert main(["run", str(run), "--sim", "--quiet"]) == 0
    assert main(["calibrate", str(run), "--ann", "--sizes", "4x4", "--folds", "2", "--epochs", "5", "--quiet",
                 "--no-report"]) == 0
    capsys.readouterr()
    assert main(["diagnose", str(run), "--json", "--folds", "3", "--candidates", "drift", "--no-report"]) == 0
    strict_loads(capsys.readouterr().out)
    found = []
    for root, _, files in os.walk(run, followlinks=True):
        for name in files:
            if name.endswith(".json"):
                path = os.path.join(root, name)
                found.append(os.path.relpath(path, run))
                doc = strict_loads(open(path).read())
                assert not _non_finite(doc), path
    names = {os.path.basename(f) for f in found}
    assert {"summary.json", "metrics.json", "history.json", "ann_cv.json", "diagnosis.json"} <= names, found


def _non_finite(obj) -> bool:
    if isinstance(obj, float):
        return not math.isfinite(obj)
    if isinstance(obj, dict):
        return any(_non_finite(v) for v in obj.values())
    if isinstance(obj, list):
        return any(_non_finite(v) for v in obj)
    return False
