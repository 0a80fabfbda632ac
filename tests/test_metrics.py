import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.metrics import CORRECT, FAIL, INCOMPLETE, WRONG


def _scenes(truth, xy=None):
    truth = np.asarray(truth, np.int32)
    b, n = truth.shape
    valid = truth != -9
    truth = np.where(valid, truth, -1)
    if xy is None:
        xy = np.zeros((b, n, 2), np.float32) + 511.5
    return js.Scene(xy=jnp.asarray(xy, jnp.float32), mag=jnp.zeros((b, n)),
                    truth=jnp.asarray(truth), valid=jnp.asarray(valid),
                    attitude=jnp.broadcast_to(jnp.eye(3), (b, 3, 3)),
                    overflow=jnp.zeros(b, bool))


def _result(ids, ok):
    return js.Identification(ids=jnp.asarray(ids, jnp.int32), ok=jnp.asarray(ok))


def test_strict_outcomes_hand_built():
    # -9 marks padding; -1 a false star
    truth = [[1, 2, 3, -1],   # all three correct, false star unnamed → correct
             [1, 2, 3, -1],   # false star named → wrong
             [1, 2, 3, -1],   # one id swapped → wrong
             [1, 2, 3, -9],   # not ok → fail
             [1, 2, 3, -9],   # only two named → incomplete
             [-1, -1, -9, -9]]  # false stars only, nothing named, ok → incomplete
    ids = [[1, 2, 3, -1], [1, 2, 3, 7], [1, 3, 3, -1], [1, 2, 3, -1], [1, 2, -1, -1],
           [-1, -1, -1, -1]]
    ok = [True, True, True, False, True, True]
    out = js.scene_outcomes(_scenes(truth), _result(ids, ok))
    np.testing.assert_array_equal(np.asarray(out["outcome"]),
                                  [CORRECT, WRONG, WRONG, FAIL, INCOMPLETE, INCOMPLETE])
    np.testing.assert_array_equal(np.asarray(out["n_correct"]), [3, 3, 2, 3, 2, 0])
    np.testing.assert_array_equal(np.asarray(out["n_wrong"]), [0, 1, 1, 0, 0, 0])
    rep = js.evaluate(_scenes(truth), _result(ids, ok))
    assert rep["identification_rate"] == pytest.approx(1 / 6)
    assert rep["failure_rate"] == pytest.approx(1 / 6)
    assert rep["misid_rate"] == pytest.approx(2 / 6)
    assert rep["accuracy"] == pytest.approx(1 / 5)
    assert rep["incomplete_rate"] == pytest.approx(2 / 6)


def test_padding_ids_are_ignored():
    out = js.scene_outcomes(_scenes([[1, 2, 3, -9]]), _result([[1, 2, 3, 44]], [True]))
    assert int(out["outcome"][0]) == CORRECT


def test_sgm_criterion_uses_neighbor_circle():
    cam = js.camera_preset("sgm2022")
    # main star at the centre; star 2 at ~3° (inside r = 6°), star 3 at ~9° (outside)
    px_per_deg = cam.f_px * np.tan(np.radians(1.0))
    xy = np.array([[[cam.cx, cam.cy], [cam.cx + 3 * px_per_deg, cam.cy],
                    [cam.cx + 9.2 * px_per_deg, cam.cy]]])
    scenes = _scenes([[10, 20, 30]], xy)
    both = js.scene_outcomes(scenes, _result([[10, 20, -1]], [True]), "sgm", camera=cam)
    assert int(both["outcome"][0]) == CORRECT  # star outside the circle may stay unnamed
    miss_inner = js.scene_outcomes(scenes, _result([[10, -1, 30]], [True]), "sgm", camera=cam)
    assert int(miss_inner["outcome"][0]) == INCOMPLETE
    with pytest.raises(ValueError, match="camera"):
        js.scene_outcomes(scenes, _result([[10, 20, -1]], [True]), "sgm")


def test_rpnet_criterion_needs_main_star():
    cam = js.camera_preset("rpnet2019")
    xy = np.array([[[cam.cx + 1, cam.cy], [cam.cx + 200, cam.cy], [cam.cx, cam.cy + 300]]])
    scenes = _scenes([[10, 20, 30]], xy)
    good = js.scene_outcomes(scenes, _result([[10, -1, -1]], [True]), "rpnet", camera=cam)
    bad = js.scene_outcomes(scenes, _result([[-1, 20, 30]], [True]), "rpnet", camera=cam)
    assert int(good["outcome"][0]) == CORRECT and int(bad["outcome"][0]) == INCOMPLETE


def test_unknown_criterion_and_shape_mismatch():
    with pytest.raises(ValueError, match="criterion"):
        js.evaluate(_scenes([[1, 2, 3]]), _result([[1, 2, 3]], [True]), "best")
    with pytest.raises(ValueError, match="shapes"):
        js.evaluate(_scenes([[1, 2, 3]]), _result([[1, 2]], [True]))


def test_oracle_harness_rates(catalog6, sgm_camera):
    import jax

    scenes = js.simulate(jax.random.key(0), catalog6, sgm_camera,
                         js.NoiseConfig(position_sigma_px=1.0, n_false=2), batch_size=2000)
    oracle = js.algorithms.get("oracle")
    cfg = oracle.Config(fail_fraction=0.2, wrong_fraction=0.1, seed=3)
    rep = js.evaluate(scenes, oracle.identify(oracle.build_database(catalog6, sgm_camera, cfg),
                                              scenes, cfg))
    assert rep["failure_rate"] == pytest.approx(0.2, abs=0.03)
    assert rep["misid_rate"] == pytest.approx(0.8 * 0.1, abs=0.02)
    perfect = oracle.identify(oracle.build_database(catalog6, sgm_camera), scenes)
    rep = js.evaluate(scenes, perfect)
    assert rep["misid_rate"] == 0.0 and rep["failure_rate"] == 0.0
    assert rep["identification_rate"] == pytest.approx(np.mean(np.asarray(
        jnp.sum(scenes.valid & (scenes.truth >= 0), -1) >= 3)))


def test_attitude_statistics_reported(catalog6, sgm_camera):
    import dataclasses

    import jax

    scenes = js.simulate(jax.random.key(1), catalog6, sgm_camera,
                         js.NoiseConfig(position_sigma_px=0.3), batch_size=100)
    oracle = js.algorithms.get("oracle")
    res = oracle.identify(oracle.build_database(catalog6, sgm_camera), scenes)
    att, _, _ = js.estimate_attitude(catalog6, sgm_camera, scenes, res)
    rep = js.evaluate(scenes, dataclasses.replace(res, attitude=att))
    assert 0 < rep["boresight_err_arcsec_median"] < 10
    assert rep["roll_err_arcsec_p95"] > rep["roll_err_arcsec_median"]


def test_registry():
    assert "oracle" in js.algorithms.names()
    with pytest.raises(ValueError, match="unknown algorithm"):
        js.algorithms.get("tetra")
