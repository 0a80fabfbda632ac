"""The twin check (:mod:`jstarid.twin`, ``jstarid twin``): a labelled set drawn from a known detection
model is fitted back, its twin simulated, and every algorithm scored on both."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid import cli, twin
from jstarid.centroid_files import read_centroid_set
from jstarid.metrics import CORRECT, OUTCOME_NAMES, WRONG, wilson_interval

CAMERA = "mlv2021"  # 25°, V ≤ 5.5: a small database
ZERO_POINT = 14.0  # the file's magnitudes: catalog V + this (an instrumental scale)
SCENES = 40
NOISE = js.NoiseConfig(position_sigma_px=0.2, magnitude_sigma=0.05, false_mean=2.0, false_mag_min=4.0,
                       false_mag_max=7.0)


def _mlv_entry():
    return js.Entry("mlv", "mlv", js.algorithms.get("mlv").Config(n_boresights=20_000, batch_chunk=100))


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """``(path, scenes, model)``: a labelled CSV of SCENES scenes drawn from the sensor's model with
    clutter, the scenes themselves and the model."""
    camera = js.camera_preset(CAMERA)
    model = js.DetectionModel.from_sensor(camera)
    catalog = js.load_catalog(8.0)
    scenes = jax.device_get(js.simulate(jax.random.key(11), catalog, camera, NOISE, batch_size=SCENES,
                                        capacity=512, detection=model))
    assert not np.asarray(scenes.overflow).any()
    lines = ["scene,x,y,mag,hip"]
    for b in range(SCENES):
        valid = np.asarray(scenes.valid[b])
        truth = np.asarray(scenes.truth[b])[valid]
        hip = np.where(truth >= 0, catalog.hip[np.maximum(truth, 0)], -1)
        for (x, y), m, h in zip(np.asarray(scenes.xy[b])[valid], np.asarray(scenes.mag[b])[valid], hip,
                                strict=True):
            lines.append(f"s{b},{x:.4f},{y:.4f},{m + ZERO_POINT:.4f},{h}")
    path = tmp_path_factory.mktemp("twin") / "labelled.csv"
    path.write_text("\n".join(lines) + "\n")
    return path, scenes, model


@pytest.fixture(scope="module")
def fitted(labelled):
    path, _, _ = labelled
    return twin.fit_labelled(read_centroid_set(path), js.camera_preset(CAMERA))


def test_fit_recovers_the_attitudes_and_the_model(labelled, fitted):
    _, scenes, model = labelled
    assert fitted.solved.all()
    # the attitude from the labels: as close to the true one as the noise allows (88″/px, ≈ 0.65 px RMS
    # over ~150 stars: the roll about the boresight, σ / (r √n) with r ≈ 400 px, is off by ≈ 25″)
    turn = np.einsum("bij,bkj->bik", fitted.attitudes, np.asarray(scenes.attitude, np.float64))
    # ‖R − I‖_F = 2√2 sin(θ/2) ≈ √2 θ (arccos of the trace loses float32's last digits: ~100″)
    angle = np.degrees(np.linalg.norm(turn - np.eye(3), axis=(1, 2)) / np.sqrt(2)) * 3600
    assert angle.max() < 60.0 and np.median(angle) < 25.0, angle
    # and it is the least-squares attitude of those labels: SciPy's Wahba solution (align_vectors)
    camera, catalog = js.camera_preset(CAMERA), js.load_catalog(12.5, sim_margin=0.0)
    found = read_centroid_set(labelled[0])
    for i in range(0, SCENES, 7):
        rows = catalog.row_of_hip(found.hip[i])
        star = rows >= 0
        body = np.asarray(camera.unproject(found.xy[i][star]), np.float64)
        reference, _ = Rotation.align_vectors(body, catalog.unit_vectors[rows[star]])
        gap = np.linalg.norm(fitted.attitudes[i] - reference.as_matrix()) / np.sqrt(2)
        assert np.degrees(gap) * 3600 < 1.0
    fit = fitted.fit
    assert abs(fit.magnitude_offset - ZERO_POINT) < 0.05
    truth_half = model.faintest_detectable(NOISE.magnitude_sigma, odds=0.5)
    assert abs(fit.model.faintest_detectable(fit.magnitude_sigma, odds=0.5) - truth_half) < 0.25
    assert 0.1 < fit.position_sigma_px < 0.35
    assert 1.4 < fit.clutter["false_mean"] < 2.6  # Poisson(2) over 40 scenes: ± 0.22 (1σ)
    assert 3.5 < fit.clutter["false_mag_min"] and fit.clutter["false_mag_max"] < 7.5
    assert np.array_equal(fitted.detections, np.asarray(scenes.n_stars))


def test_twin_check_scores_both_sets_as_the_engine_does(labelled, fitted):
    path, scenes, _ = labelled
    found = read_centroid_set(path)
    check = twin.twin_check(found, js.camera_preset(CAMERA), ["oracle", _mlv_entry()], scenes=60, seed=2,
                            catalog=js.load_catalog(5.5), progress=False)
    assert check.result.levels == [{"twin": 0}, {"twin": 1}]
    assert np.bincount(check.result.level_of).tolist() == [SCENES, 60]
    # the twin looks like the set: as many detections per scene, within 15 %
    assert abs(check.detections["twin"] / check.detections["real"] - 1) < 0.15
    outcome = check.result.scenes["outcome"]
    for row in check.rows():
        e = check.result.labels.index(row["label"])
        for side, level in (("real", 0), ("twin", 1)):
            code = outcome[check.result.level_of == level, e]
            k = int(np.sum(code == CORRECT))
            assert row[f"{side}_identification"] == k / code.size
            lo, hi = wilson_interval(k, code.size)
            assert (row[f"{side}_identification_low"], row[f"{side}_identification_high"]) == (lo, hi)
            assert row[f"{side}_misid"] == np.mean(code == WRONG)
        real_lo, real_hi = row["real_identification_low"], row["real_identification_high"]
        assert row["identification_agrees"] == (real_lo <= row["twin_identification"] <= real_hi)
    oracle = check.rows()[0]
    assert oracle["real_identification"] == 1.0 and oracle["twin_identification"] == 1.0
    table = check.table()
    assert "| mlv |" in table and "50 % complete at V" in table
    # the real scenes carry the fitted attitudes: MLV's boresight errors are arcseconds
    err = check.result.scenes["boresight_err_arcsec"][check.result.level_of == 0, 1]
    assert np.nanmedian(err) < 30.0
    # scene by scene: twin scene j was drawn from real scene j mod 40; the shares add up to the rate
    scene_rows = check.scene_rows()
    assert [r["scene"] for r in scene_rows] == [f"s{b}" for b in range(SCENES)]
    counts = np.array([r["twin_scenes"] for r in scene_rows])
    assert counts.sum() == 60 and set(counts.tolist()) == {1, 2}
    real_codes = outcome[check.result.level_of == 0, 1]
    assert [r["mlv_real"] for r in scene_rows] == [OUTCOME_NAMES[int(c)] for c in real_codes]
    mlv = check.rows()[1]
    share = np.array([r["mlv_twin"] for r in scene_rows])
    assert np.isclose(np.sum(share * counts) / 60, mlv["twin_identification"])
    assert all(r["oracle_real"] == "correct" and r["oracle_twin"] == 1.0 for r in scene_rows)


def test_exact_sky_draws_the_labelled_attitudes(labelled, fitted):
    """sky="exact": twin scene j at real scene j mod R's attitude, its stars those the real scene
    labelled (new detections of the same sky)."""
    camera, catalog = js.camera_preset(CAMERA), js.load_catalog(5.5)
    scenes, _, _ = twin.twin_scenes(fitted, camera, catalog, scenes=SCENES + 2, seed=3, capacity=64,
                                    sky="exact")
    source = np.arange(SCENES + 2) % SCENES
    np.testing.assert_allclose(np.asarray(scenes.attitude), fitted.attitudes[source], atol=1e-6)
    found = read_centroid_set(labelled[0])
    for j in (0, SCENES + 1):
        truth = np.asarray(scenes.truth[j])[np.asarray(scenes.valid[j])]
        named = set(catalog.hip[truth[truth >= 0]].tolist())
        assert len(named) >= 5 and len(named & set(found.hip[source[j]].tolist())) >= 0.8 * len(named)
    with pytest.raises(ValueError, match="sky must be one of"):
        twin.twin_scenes(fitted, camera, catalog, scenes=2, sky="nearby")


def test_twin_refuses_sets_it_cannot_fit(tmp_path):
    camera = js.camera_preset(CAMERA)
    (tmp_path / "nolabels.csv").write_text("x,y,mag\n1,2,3\n4,5,6\n")
    with pytest.raises(ValueError, match="needs a labelled set"):
        twin.fit_labelled(read_centroid_set(tmp_path / "nolabels.csv"), camera)
    (tmp_path / "nomags.csv").write_text("x,y,hip\n1,2,3\n4,5,6\n")
    with pytest.raises(ValueError, match="needs measured brightness"):
        twin.fit_labelled(read_centroid_set(tmp_path / "nomags.csv"), camera)
    (tmp_path / "few.csv").write_text("x,y,mag,hip\n1,2,3,-1\n4,5,6,32349\n")
    with pytest.raises(ValueError, match="3 or more labelled catalog stars"):
        twin.fit_labelled(read_centroid_set(tmp_path / "few.csv"), camera)


def test_cli_twin(labelled, tmp_path, capsys):
    path, _, _ = labelled
    out = tmp_path / "out"
    assert cli.main(["twin", str(path), "--camera", CAMERA, "--algorithms", "oracle", "--scenes", "30",
                     "--sky", "random", "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "| oracle | 100.0 % [91.2–100.0] of 40 |" in printed
    saved = json.loads((out / "twin.json").read_text())
    assert saved["scenes_fitted"] == SCENES and saved["sky"] == "random"
    assert saved["rows"][0]["twin_scenes"] == 30 and saved["scenes"] == []  # scene by scene: real, exact
    assert (out / "table.md").read_text().startswith("| algorithm | real identified")
    # an unlabelled file: one line, status 2
    (tmp_path / "bare.csv").write_text("x,y,mag\n1,2,3\n")
    assert cli.main(["twin", str(tmp_path / "bare.csv"), "--camera", CAMERA]) == 2
    err = capsys.readouterr().err
    assert "has no true ids" in err and err.count("\n") == 1


def test_near_attitudes_stay_near_and_roll_freely():
    camera = js.camera_preset(CAMERA)
    base = Rotation.random(3, random_state=2).as_matrix()
    near = twin.near_attitudes(base, camera, 300, seed=1)
    assert near.shape == (300, 3, 3)
    np.testing.assert_allclose(np.einsum("bij,bkj->bik", near, near), np.broadcast_to(np.eye(3), near.shape),
                               atol=1e-12)
    mine = base[np.arange(300) % 3]
    tilt = np.degrees(np.arccos(np.clip(np.einsum("bi,bi->b", near[:, 2], mine[:, 2]), -1, 1)))
    assert tilt.max() <= np.hypot(1, 1) * camera.fov_y_deg / 4 + 1e-6 and tilt.mean() > camera.fov_y_deg / 16
    # the roll: the angle between the camera x axes, spread over the whole circle
    roll = np.degrees(np.arctan2(np.einsum("bi,bi->b", near[:, 0], mine[:, 1]),
                                 np.einsum("bi,bi->b", near[:, 0], mine[:, 0])))
    assert np.histogram(roll, bins=4, range=(-180, 180))[0].min() > 40
    np.testing.assert_array_equal(near, twin.near_attitudes(base, camera, 300, seed=1))


def test_train_on_fit_trains_what_trains_on_the_fitted_model(fitted):
    """``train_on_fit``: RpNet's config trains on the fitted model (its own network); an algorithm
    that trains nothing keeps its config."""
    camera = js.camera_preset("tetra3_test")
    entries = js.engine.entries("rpnet,mlv", camera=camera)
    model = fitted.fit.model
    rpnet_entry, mlv_entry = (twin._trained_on(e, model) for e in entries)
    assert rpnet_entry.config.train_detection == model and rpnet_entry.label == entries[0].label
    assert rpnet_entry.config.fingerprint() != entries[0].config.fingerprint()  # a network of its own
    assert mlv_entry == entries[1]
