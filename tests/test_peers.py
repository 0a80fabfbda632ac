"""The cedar-solve peer's host side (jstarid.peers.cedar), without cedar itself: the suite never
builds the peer's environment."""

import csv
from pathlib import Path

import numpy as np
import pytest

import jstarid as js
from jstarid.peers import PEERS, cedar


def test_conversions_round_trip(tmp_path, catalog6, key):
    """hip_main.dat read back as cedar reads it ('|' fields 1, 5, 8, 9), centroids in cedar's (y, x)
    corner-origin convention brightest first, and matches mapped back to detections and rows."""
    small = js.load_catalog(3.0)
    path = tmp_path / "hip_main.dat"
    cedar.write_hip_main(small, path)
    rows = list(csv.reader(path.open(), delimiter="|"))
    assert len(rows) == len(small)
    np.testing.assert_array_equal([int(r[1]) for r in rows], small.hip)
    np.testing.assert_allclose([float(r[5]) for r in rows], small.mag, atol=0.006)
    np.testing.assert_allclose(np.radians([float(r[9]) for r in rows]), small.dec, atol=1e-9)
    scenes = js.simulate(key, catalog6, js.camera_preset("sgm2022"), js.noise_grid(2), batch_size=2,
                         capacity=32)
    cedar.export_scenes(scenes, tmp_path / "c.npz")
    data = np.load(tmp_path / "c.npz")
    xy, mag, valid = (np.asarray(a)[0] for a in (scenes.xy, scenes.mag, scenes.valid))
    brightest = np.argmin(np.where(valid, mag, np.inf))
    np.testing.assert_allclose(data["centroids"][0, 0], xy[brightest, ::-1] + 0.5)
    assert int(data["counts"][0]) == int(valid.sum())
    # cedar "matches" the three brightest detections of scene 0 with their true HIP numbers
    order = data["order"][0, :3]
    truth = np.asarray(scenes.truth)[0, order]
    solved = {"solved": [True, False], "matched": [data["centroids"][0, :3].tolist(), []],
              "ids": [catalog6.hip[truth].tolist(), []], "seconds": [0.01, 0.02]}
    ids, ok = cedar.matches_to_ids(scenes, catalog6, solved)
    np.testing.assert_array_equal(ids[0, order], truth)
    assert np.sum(ids[0] >= 0) == 3 and np.all(ids[1] == -1) and list(ok) == [True, False]


def test_the_peer_keeps_the_contract_and_stays_out_of_the_registry():
    assert "cedar" not in js.algorithms.names()
    js.algorithms.base.check_algorithm(cedar, "cedar")
    assert PEERS["cedar"] == cedar.__name__
    with pytest.raises(ValueError):
        cedar.Config(match_max_error=0.0)


def test_a_peer_is_a_row_per_reported_setting_and_set_replaces_the_grid(monkeypatch, capsys):
    from jstarid.cli import sweeps

    monkeypatch.setattr(js.algorithms, "_REGISTRY", dict(js.algorithms._REGISTRY))  # no leak
    monkeypatch.setattr(cedar, "environment", lambda **_: None)
    assert sweeps._available_peers(["cedar"]) == []
    assert "not available; going on without it" in capsys.readouterr().out
    monkeypatch.setattr(cedar, "environment", lambda **_: Path("python"))
    assert sweeps._available_peers(["cedar", "cedar"]) == ["cedar"]
    entry = js.engine.entries(["cedar"])[0]
    rows = sweeps._reported(entry, {})
    assert [e.config.match_max_error for e in rows] == list(cedar.REPORTED["match_max_error"])
    assert [e.label for e in rows] == ["cedar match_max_error=0.002", "cedar match_max_error=0.005"]
    assert len(sweeps._reported(entry, {"mlv.match_max_error": "0.1"})) == 2  # another algorithm's
    assert sweeps._reported(entry, {"cedar.match_max_error": "0.003"}) == [entry]


def test_a_peer_named_among_the_algorithms_runs_as_a_peer(monkeypatch, capsys):
    """``--algorithms mlv,cedar`` reads cedar as ``--peer cedar``: the registry's error would list
    only the algorithms, though the message of an empty list names the peers."""
    from jstarid.cli import main

    monkeypatch.setattr(js.algorithms, "_REGISTRY", dict(js.algorithms._REGISTRY))  # no leak
    monkeypatch.setattr(cedar, "environment", lambda **_: None)
    status = main(["sweep", "--algorithms", "cedar", "--camera", "sgm2022", "--levels", "1", "--scenes", "1",
                   "--quiet"])
    out = capsys.readouterr()
    assert "cedar: its environment is not available" in out.out
    assert "unknown algorithm" not in out.err
    assert status == 2
