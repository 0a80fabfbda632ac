import json

from jstarid import cli


def test_demo_writes_picture_and_stats(tmp_path, capsys):
    assert cli.main(["demo", "--batch", "20", "--out", str(tmp_path), "--false", "1"]) == 0
    stats = json.loads((tmp_path / "scene_stats.json").read_text())
    assert stats["scenes"] == 20 and stats["stars_per_scene_mean"] > 3
    assert (tmp_path / "scene.png").stat().st_size > 10_000
    assert "simulated 20 scenes" in capsys.readouterr().out


def test_compare_runs_registered_algorithms(tmp_path, capsys):
    assert cli.main(["compare", "--algorithms", "oracle", "--batch", "30", "--out",
                     str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert rows[0]["algorithm"] == "oracle" and rows[0]["misid"] == 0.0
    assert "| oracle |" in capsys.readouterr().out


def test_bad_input_is_a_clear_error(capsys):
    assert cli.main(["demo", "--camera", "nope"]) == 2
    assert "unknown camera preset" in capsys.readouterr().err
    assert cli.main(["compare", "--algorithms", "nope", "--batch", "5"]) == 2
    assert cli.main(["demo", "--sigma", "-1", "--batch", "5"]) == 2


def test_list(capsys):
    assert cli.main(["list"]) == 0
    assert "oracle" in capsys.readouterr().out
