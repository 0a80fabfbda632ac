"""Smoke tests of the experiment scripts at tiny sizes (slow: run with ``pytest -m slow``)."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the class is created
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_tune_sgm_tiny(tmp_path):
    _load("tune_sgm").main(["--scenes", "4", "--cs", "1.0", "1.74", "--eps", "0.2", "0.4",
                            "--out", str(tmp_path)])
    res = json.loads((tmp_path / "results.json").read_text())
    assert len(res["grid"]) == 4 and len(res["fig11"]) == 7
    assert (tmp_path / "fig12_13_eps.png").exists() and (tmp_path / "table.md").exists()
