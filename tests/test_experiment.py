"""The experiment harness (jstarid.experiment): overrides, results directory, tables, timing."""

import json

import numpy as np
import pytest

import jstarid as js
from jstarid import experiment as ex


def test_overrides_are_json_checked_against_the_config():
    cfg = ex.with_overrides(js.NoiseConfig(), ["position_sigma_px=1.5", "n_false=2"])
    assert cfg.position_sigma_px == 1.5 and cfg.n_false == 2
    assert ex.with_overrides(cfg, {"n_false": 0}).n_false == 0
    assert ex.with_overrides(cfg, []) is cfg
    with pytest.raises(ValueError, match="no field 'sigma'"):
        ex.with_overrides(cfg, ["sigma=1"])
    with pytest.raises(ValueError, match="JSON"):
        ex.with_overrides(cfg, ["position_sigma_px=one"])
    with pytest.raises(ValueError, match="FIELD=VALUE"):
        ex.with_overrides(cfg, ["position_sigma_px"])


def test_parser_has_the_shared_options(tmp_path):
    args = ex.parser("x", out=str(tmp_path), seed=3, quick="fewer scenes").parse_args(
        ["--quick", "--set", "a=1", "b=true"])
    assert args.quick and args.seed == 3 and args.out == tmp_path and args.set == ["a=1", "b=true"]


def test_write_and_load_a_results_directory(tmp_path):
    drawn = []

    def draw(results, path):  # figures see the saved results, not the in-memory ones
        drawn.append(results)
        path.write_bytes(b"png")

    rows = [{"level": 0.5, "rate": 0.991, "misid": 0.0},
            {"level": 1.0, "rate": np.float32(0.5), "misid": None}]
    out = ex.write(tmp_path / "run", config={"camera": js.camera_preset("sgm2022"), "seed": 1},
                   results={"rows": rows, "nan": float("nan"), "array": np.arange(3)},
                   table=ex.markdown_table(rows, [("level", "σ (px)", "{:g}"), ("rate", "rate", "{:.1%}"),
                                                  ("misid", "misid", "{:.2%}")], title="T"),
                   figures={"fig.png": draw})
    config, results = ex.load(out)
    assert config["seed"] == 1 and config["camera"]["name"] == "sgm2022"
    assert {"commit", "machine", "command", "date"} <= set(config["provenance"])
    assert results["nan"] is None and results["array"] == [0, 1, 2]
    assert drawn == [json.loads((out / "results.json").read_text())] and (out / "fig.png").exists()
    table = (out / "table.md").read_text()
    assert "| 0.5 | 99.1% | 0.00% |" in table and "| 1 | 50.0% | – |" in table


def test_time_call_reports_first_and_steady_seconds():
    calls = []
    first, steady = ex.time_call(lambda i: calls.append(i) or np.zeros(3), repeats=3)
    assert calls == [0, 1, 2, 3] and first >= 0 and steady >= 0
    assert ex.peak_rss_mb() > 0
