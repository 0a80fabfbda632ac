import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jstarid as js


def test_quaternion_round_trip_matches_scipy():
    rot = Rotation.random(200, random_state=3)
    q = rot.as_quat()  # scalar-last
    c = np.asarray(js.rotation_from_quaternion(jnp.asarray(q)))
    np.testing.assert_allclose(c, rot.as_matrix(), atol=1e-5)
    q_back = np.asarray(js.quaternion_from_rotation(jnp.asarray(rot.as_matrix(), jnp.float32)))
    q_ref = q * np.where(q[:, 3:] < 0, -1, 1)
    np.testing.assert_allclose(q_back, q_ref, atol=1e-5)


def test_random_rotation_is_proper_and_uniform():
    c = np.asarray(js.random_rotation(jax.random.key(1), (20000,)))
    np.testing.assert_allclose(np.linalg.det(c), 1.0, atol=1e-4)
    np.testing.assert_allclose(c @ c.transpose(0, 2, 1), np.broadcast_to(np.eye(3), c.shape),
                               atol=1e-5)
    # Haar measure: every matrix entry has mean 0 and variance 1/3
    np.testing.assert_allclose(c.mean(0), 0.0, atol=0.02)
    np.testing.assert_allclose(c.var(0), 1 / 3, atol=0.02)


def test_radec_roll_round_trip_and_convention():
    rng = np.random.default_rng(0)
    ra = rng.uniform(0, 2 * np.pi, 300)
    dec = rng.uniform(-1.5, 1.5, 300)
    roll = rng.uniform(-np.pi, np.pi, 300)
    c = js.rotation_from_radec_roll(ra, dec, roll)
    ra2, dec2, roll2 = js.rotation_to_radec_roll(c)
    np.testing.assert_allclose(np.asarray(ra2), ra, atol=1e-5)
    np.testing.assert_allclose(np.asarray(dec2), dec, atol=1e-5)
    np.testing.assert_allclose(np.angle(np.exp(1j * (np.asarray(roll2) - roll))), 0, atol=1e-4)
    # boresight is row 2 and maps to +z; roll 0 puts +x east
    c0 = np.asarray(js.rotation_from_radec_roll(0.3, 0.2, 0.0), np.float64)
    bore = np.array([np.cos(0.3) * np.cos(0.2), np.sin(0.3) * np.cos(0.2), np.sin(0.2)])
    np.testing.assert_allclose(c0 @ bore, [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(c0[0], [-np.sin(0.3), np.cos(0.3), 0], atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(c0), 1.0, atol=1e-6)


def test_wahba_recovers_rotation_like_scipy():
    rng = np.random.default_rng(5)
    truth = Rotation.random(random_state=7)
    ref = rng.normal(size=(12, 3))
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    body = truth.apply(ref) + rng.normal(scale=1e-3, size=ref.shape)
    body /= np.linalg.norm(body, axis=1, keepdims=True)
    w = rng.uniform(0.5, 2.0, 12)
    c = np.asarray(js.solve_wahba(jnp.asarray(body), jnp.asarray(ref), jnp.asarray(w)))
    est, _ = Rotation.align_vectors(body, ref, weights=w)
    np.testing.assert_allclose(c, est.as_matrix(), atol=1e-5)
    # zero weights mask pairs out
    w2 = np.concatenate([w[:6], np.zeros(6)])
    body_bad = body.copy()
    body_bad[6:] = rng.normal(size=(6, 3))
    c2 = np.asarray(js.solve_wahba(jnp.asarray(body_bad), jnp.asarray(ref), jnp.asarray(w2)))
    np.testing.assert_allclose(c2, truth.as_matrix(), atol=5e-3)


def test_attitude_errors():
    c = js.rotation_from_radec_roll(1.0, 0.5, 0.2)
    arcsec = np.pi / 180 / 3600
    c_roll = js.rotation_from_radec_roll(1.0, 0.5, 0.2 + 30 * arcsec)
    bore, roll = js.attitude_errors_arcsec(c_roll, c)
    assert float(bore) == pytest.approx(0.0, abs=0.5)
    assert float(roll) == pytest.approx(30.0, abs=0.5)
    c_tilt = js.rotation_from_radec_roll(1.0, 0.5 + 20 * arcsec, 0.2)
    bore, _ = js.attitude_errors_arcsec(c_tilt, c)
    assert float(bore) == pytest.approx(20.0, abs=0.5)


def test_estimate_attitude_from_truth(catalog6, sgm_camera):
    scenes = js.simulate(jax.random.key(3), catalog6, sgm_camera,
                         js.NoiseConfig(position_sigma_px=0.5), batch_size=64)
    oracle = js.algorithms.get("oracle")
    result = oracle.identify(oracle.build_database(catalog6, sgm_camera), scenes)
    c, resid, have = js.estimate_attitude(catalog6, sgm_camera, scenes, result)
    assert bool(np.all(np.asarray(have) == (np.asarray(scenes.n_stars) >= 2)))
    bore, roll = js.attitude_errors_arcsec(c, scenes.attitude)
    bore, roll = np.asarray(bore)[np.asarray(have)], np.asarray(roll)[np.asarray(have)]
    # 0.5 px ≈ 35″ per star on this camera; tens of stars average it down
    assert np.median(bore) < 15 and np.median(roll) < 120
    assert np.all(np.asarray(resid)[np.asarray(have)] < 120)


def test_estimate_attitude_in_calls_equals_each_scene_alone(catalog6, sgm_camera, monkeypatch):
    """20 scenes in calls of at most 16 (16 + 4, each padded to 16): each scene's attitude is what
    it gets alone, and an empty batch gives empty arrays."""
    from jstarid import attitude

    monkeypatch.setattr(attitude, "ESTIMATE_CHUNK", 16)
    scenes = js.simulate(jax.random.key(4), catalog6, sgm_camera, js.NoiseConfig(position_sigma_px=1.0),
                         batch_size=20, capacity=32)
    result = js.Identification(ids=scenes.truth, ok=np.ones(20, bool), attitude=None)
    c, resid, have = (np.asarray(a) for a in js.estimate_attitude(catalog6, sgm_camera, scenes, result))
    assert c.shape == (20, 3, 3) and resid.shape == have.shape == (20,) and have.all()
    for i in (0, 15, 16, 19):
        alone = js.estimate_attitude(catalog6, sgm_camera, scenes[i], result[i])
        np.testing.assert_allclose(np.asarray(alone[0])[0], c[i], atol=1e-6)
        np.testing.assert_allclose(np.asarray(alone[1])[0], resid[i], rtol=1e-4)
    empty = js.estimate_attitude(catalog6, sgm_camera, scenes[:0], result[:0])
    assert [np.shape(a) for a in empty] == [(0, 3, 3), (0,), (0,)]
    assert [np.asarray(a).dtype for a in empty] == [np.float32, np.float32, bool]


def test_triad_recovers_a_rotation_from_two_pairs_like_scipy():
    """TRIAD on two noise-free vector pairs gives the rotation scipy's ``align_vectors`` finds."""
    from jstarid.attitude import triad

    rng = np.random.default_rng(4)
    truth = Rotation.random(5, random_state=7).as_matrix()  # C: v_cam = C r
    r = rng.normal(size=(5, 2, 3))
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    b = np.einsum("kij,knj->kni", truth, r)
    got = np.asarray(triad(jnp.asarray(b[:, 0], jnp.float32), jnp.asarray(b[:, 1], jnp.float32),
                           jnp.asarray(r[:, 0], jnp.float32), jnp.asarray(r[:, 1], jnp.float32)))
    for k in range(5):
        ref, _ = Rotation.align_vectors(b[k], r[k])
        np.testing.assert_allclose(got[k], ref.as_matrix(), atol=2e-5)
