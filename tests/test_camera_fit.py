"""jstarid.camera_fit: the joint attitude and focal-length fit against SciPy, and its checks."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid import camera_fit as cf
from jstarid.config_tree import with_fields


@pytest.fixture(scope="module")
def world():
    return js.load_catalog(6.0), js.camera_preset("sgm2022")


def _scenes(cat, nominal, scale, n=16, seed=0, sigma=0.5):
    true = dataclasses.replace(nominal, f_px=nominal.f_px * scale)
    scenes = js.simulate(jax.random.key(seed), cat, true, js.NoiseConfig(position_sigma_px=sigma),
                         batch_size=n)
    return scenes, np.where(np.asarray(scenes.valid), np.asarray(scenes.truth), -1)


# the fits compiled whole, once per name count (the camera static): called op by op, each scene's
# name count compiled a few dozen small programs
_fit_scaled = jax.jit(cf.fit_scaled, static_argnames=("camera", "fit_scale", "iterations"))
_fit_distorted = jax.jit(cf.fit_distorted, static_argnames=("camera", "iterations"))


def _scipy_fit(xy, ref, cam):
    """Least squares over (rotation vector, scale) of the pixel residuals, float64."""
    def residuals(p):
        v = Rotation.from_rotvec(p[:3]).apply(ref)
        pred = np.array([cam.cx, cam.cy]) + p[3] * cam.f_px * v[:, :2] / v[:, 2:3]
        return (pred - xy).ravel()

    start = Rotation.align_vectors(np.asarray(cam.unproject(jnp.asarray(xy, jnp.float32)), np.float64),
                                   ref)[0].as_rotvec()
    return least_squares(residuals, np.r_[start, 1.0], xtol=1e-12, ftol=1e-12).x


@pytest.mark.parametrize("scale", [0.97, 1.02])
def test_fit_scaled_matches_scipy_least_squares(world, scale):
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, scale, n=4)
    for i in range(4):
        named = truth[i] >= 0
        xy = np.asarray(scenes.xy[i], np.float64)[named]
        ref = cat.unit_vectors[truth[i][named]]
        c, s, _ = _fit_scaled(jnp.asarray(xy, jnp.float32), jnp.asarray(ref, jnp.float32),
                              jnp.ones(len(xy), jnp.float32), nominal)
        p = _scipy_fit(xy, ref, nominal)
        assert abs(float(s) - p[3]) < 2e-5, (float(s), p[3])
        angle = np.linalg.norm((Rotation.from_matrix(np.asarray(c, np.float64))
                                * Rotation.from_rotvec(p[:3]).inv()).as_rotvec())
        assert np.degrees(angle) * 3600 < 1.0  # arcsec
        assert abs(p[3] - scale) < 2e-3  # and both find the camera the scenes were taken with


def test_verify_names_takes_back_wrong_names_and_keeps_right_ones(world):
    cat, nominal = world
    for scale in (0.95, 1.05):
        scenes, truth = _scenes(cat, nominal, scale, n=24, seed=1)
        ids = truth.copy()
        rows = np.arange(len(ids))
        first = np.argmax(ids >= 0, axis=1)
        ids[rows, first] = (ids[rows, first] + 7) % len(cat)  # a star from elsewhere in the sky
        kept, ok, fit = cf.verify_names(cat.unit_vectors, nominal, scenes.xy, scenes.valid, ids,
                                        np.ones(len(ids), bool))
        kept = np.asarray(kept)
        assert np.all(np.asarray(ok))
        assert np.all((kept < 0) | (kept == truth))  # every wrong name taken back
        right = (ids >= 0) & (ids == truth)
        assert np.sum(kept[right] >= 0) >= 0.995 * right.sum()
        np.testing.assert_allclose(np.asarray(fit.scale), scale, atol=2e-3)


def test_a_traced_camera_projects_as_the_camera_does(world):
    _, nominal = world
    cam = dataclasses.replace(nominal, cx=nominal.cx + 3.5, cy=nominal.cy - 2.0)
    xy = jnp.asarray([[0.0, 0.0], [cam.cx, cam.cy], [1000.5, 17.25], [cam.width + 2.0, 4.0]], jnp.float32)

    @jax.jit
    def traced(numbers):
        moved = js.Camera.traced(numbers)
        v = moved.unproject(xy)
        return v, moved.project(v)[0], moved.contains(xy)

    v, back, inside = traced(cam.pinhole_numbers())
    np.testing.assert_allclose(v, cam.unproject(xy), atol=1e-7)
    np.testing.assert_allclose(back, cam.project(cam.unproject(xy))[0], atol=1e-3)
    np.testing.assert_array_equal(inside, cam.contains(xy))


def test_another_camera_of_the_same_shapes_compiles_nothing(world):
    """The check's kernels take the camera as traced numbers: one program serves every camera."""
    from jstarid.runtime import CountCompilations

    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=4, seed=2)
    ok = np.ones(4, bool)
    first = cf.verify_names(cat.unit_vectors, nominal, scenes.xy, scenes.valid, truth, ok)
    jax.block_until_ready(first)
    other = dataclasses.replace(nominal, f_px=nominal.f_px * 1.02, cx=nominal.cx + 4.0, cy=nominal.cy - 3.0)
    with CountCompilations() as count:
        kept, solved, fit = cf.verify_names(cat.unit_vectors, other, scenes.xy, scenes.valid, truth, ok)
        jax.block_until_ready((kept, solved, fit))
    assert count.programs == 0, f"{count.programs} programs compiled for another camera"
    assert np.all(np.asarray(first[1]))
    np.testing.assert_allclose(np.asarray(first[2].scale), 1.0, atol=2e-3)
    np.testing.assert_allclose(np.asarray(fit.scale)[np.asarray(solved)], 1 / 1.02, atol=4e-3)


def test_empty_columns_change_nothing(world):
    """The check's calls are cut to the columns the detections fill: the same scenes with twice the
    capacity (empty columns after the detections) give the same names, claims and fits."""
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=4, seed=3)
    ids = np.where(np.cumsum(truth >= 0, axis=1) <= 6, truth, -1)  # six names: the field check runs
    ok = np.ones(4, bool)
    n = scenes.capacity
    wide = [np.pad(np.asarray(a), [(0, 0), (0, n)] + [(0, 0)] * (np.ndim(a) - 2))
            for a in (scenes.xy, scenes.valid, ids)]
    kept, solved, fit = cf.verify_names(cat.unit_vectors, nominal, scenes.xy, scenes.valid, ids, ok)
    kept_w, solved_w, fit_w = cf.verify_names(cat.unit_vectors, nominal, *wide, ok)
    assert np.asarray(solved).any()
    np.testing.assert_array_equal(np.asarray(kept_w)[:, :n], kept)
    assert np.all(np.asarray(kept_w)[:, n:] == -1)
    np.testing.assert_array_equal(solved_w, solved)
    np.testing.assert_allclose(np.asarray(fit_w.attitude), np.asarray(fit.attitude), atol=1e-6)


def test_a_wrong_sky_fails_the_field_check(world):
    """Four names that fit a wrong attitude exactly (their detections moved to where that attitude
    puts them): every name fits, but the frame's other bright stars are missing."""
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=8, seed=2, sigma=0.0)
    names = np.full_like(truth, -1)
    xy = np.array(scenes.xy)
    other = np.asarray(js.attitude.random_rotation(jax.random.key(9), (8,)))
    for i in range(8):
        v = cat.unit_vectors @ other[i].T
        pred, inside = (np.asarray(a) for a in nominal.project(jnp.asarray(v, jnp.float32)))
        rows = np.flatnonzero(inside)[:4]  # the wrong sky's four brightest stars
        det = np.flatnonzero(truth[i] >= 0)[:4]
        names[i, det], xy[i, det] = rows, pred[rows]
    moved = dataclasses.replace(scenes, xy=jnp.asarray(xy))
    kept, ok, _ = cf.verify_names(cat.unit_vectors, nominal, moved.xy, moved.valid, names,
                                  np.ones(8, bool))
    assert not np.any(np.asarray(ok)) and np.all(np.asarray(kept) == -1)
    _, ok_true, _ = cf.verify_names(cat.unit_vectors, nominal, scenes.xy, scenes.valid, truth,
                                    np.ones(8, bool))
    assert np.all(np.asarray(ok_true))


def test_a_name_far_brighter_than_its_star_is_taken_back(world):
    """The RpNet case: a bright false star on the spot of an undetected faint star fits the geometry.
    Each scene's faintest name is made 3 mag brighter; with the catalog magnitudes only it goes,
    under any zero point, and a bright star read 3 mag too faint (saturation) keeps its name."""
    cat, nominal = world
    scenes = js.simulate(jax.random.key(4), cat, nominal,
                         js.NoiseConfig(position_sigma_px=0.5, magnitude_sigma=0.2), batch_size=16)
    truth = np.where(np.asarray(scenes.valid), np.asarray(scenes.truth), -1)
    rows = np.arange(16)
    faintest = truth.shape[1] - 1 - np.argmax((truth >= 0)[:, ::-1], axis=1)
    brightest = np.argmax(truth >= 0, axis=1)
    mag = np.array(scenes.mag)
    mag[rows, faintest] -= 3.0
    mag[rows, brightest] += 3.0
    moved = dataclasses.replace(scenes, mag=jnp.asarray(mag + 12.5))  # instrumental zero point
    claim = js.Identification(ids=jnp.asarray(truth), ok=jnp.ones(16, bool))
    ids, ok, _, _ = cf.check_claims(cat.unit_vectors, nominal, moved, claim, star_mags=cat.mag)
    ids = np.asarray(ids)
    assert np.all(np.asarray(ok)) and np.all((ids < 0) | (ids == truth))
    assert np.all(ids[rows, faintest] == -1) and np.all(ids[rows, brightest] == truth[rows, brightest])
    others = (truth >= 0)
    others[rows, faintest] = False
    assert np.sum(ids[others] >= 0) >= 0.995 * others.sum()
    geometry_only, _, _, _ = cf.check_claims(cat.unit_vectors, nominal, moved, claim)
    assert np.all(np.asarray(geometry_only)[rows, faintest] == truth[rows, faintest])


def test_rescaled_scenes_read_as_the_scaled_camera(world):
    cat, nominal = world
    scenes, _ = _scenes(cat, nominal, 1.0, n=2)
    moved = cf.rescale_scenes(scenes, nominal, 0.98)
    scaled = dataclasses.replace(nominal, f_px=nominal.f_px * 0.98)
    valid = np.asarray(scenes.valid)
    np.testing.assert_allclose(np.asarray(nominal.unproject(moved.xy))[valid],
                               np.asarray(scaled.unproject(scenes.xy))[valid], atol=2e-6)


def test_search_focal_retries_only_unsolved_scenes(world, monkeypatch):
    monkeypatch.setattr(cf, "FEW_RETRIES", 0)  # one call per factor
    monkeypatch.setattr(cf, "BATCH_RETRIES", 0)
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=4)
    calls = []

    def run(moved, rows):
        calls.append((rows.tolist(), np.asarray(moved.valid).any(axis=1).tolist()))
        return js.Identification(ids=jnp.asarray(truth[rows]), ok=jnp.asarray(rows != 3))

    first = js.Identification(ids=jnp.full(truth.shape, -1), ok=jnp.array([True, False, True, False]))
    out = cf.search_focal(run, first, scenes, nominal, (0.99, 1.01))
    # the second factor sees only what is left; each retry is padded to 16 scenes (the smallest
    # call of the algorithms' kernels: a few retries compile nothing a small batch has not;
    # runtime.padded_indices, copies of the first row) with empty scenes, which fail at once
    # instead of repeating a search
    assert cf.RETRY_FLOOR == 16
    assert [c[0] for c in calls] == [[1, 3] + [1] * 14, [3] * 16]
    assert [c[1] for c in calls] == [[True, True] + [False] * 14, [True] + [False] * 15]
    np.testing.assert_array_equal(np.asarray(out.ok), [True, True, True, False])
    np.testing.assert_array_equal(np.asarray(out.ids[1]), truth[1])
    assert np.all(np.asarray(out.ids[3]) == -1)


def test_search_focal_in_one_call_keeps_the_first_factor_that_solves(world, monkeypatch):
    """Few retries run every factor in one call; each scene gets what the sequential ladder gives."""
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=6)
    scales = (0.99, 1.01, 0.98)
    # which factor solves which scene: scene 1 by 1.01 and 0.98 (1.01 comes first), scene 3 by
    # 0.98 alone, scene 5 by none; the ids tell the factor apart
    solves = {(1, 1.01), (1, 0.98), (3, 0.98)}

    def run(moved, rows):
        # the factor of each row, read back from how far the moved centroid left the centre
        centre = np.array([nominal.cx, nominal.cy])
        valid = np.asarray(moved.valid)
        k = np.argmax(valid, axis=1)
        orig = np.asarray(scenes.xy)[rows, k] - centre
        now = np.asarray(moved.xy)[np.arange(len(rows)), k] - centre
        factor = np.round(np.linalg.norm(orig, axis=1) / np.linalg.norm(now, axis=1), 4)
        ok = np.array([(int(r), float(f)) in solves for r, f in zip(rows, factor, strict=True)])
        ids = np.where(ok[:, None], truth[rows], -1)
        ids = np.where((factor[:, None] == 0.98) & (ids >= 0), ids + 1000, ids)
        calls.append(len(rows))
        att = np.broadcast_to(factor[:, None, None], (len(rows), 3, 3))
        return js.Identification(ids=jnp.asarray(ids), ok=jnp.asarray(ok), attitude=jnp.asarray(att))

    first = js.Identification(ids=jnp.full(truth.shape, -1),
                              ok=jnp.array([True, False, True, False, True, False]),
                              attitude=jnp.full((6, 3, 3), np.nan))
    results = []
    for few in (64, 0):  # one call, then one call per factor
        monkeypatch.setattr(cf, "FEW_RETRIES", few)
        monkeypatch.setattr(cf, "BATCH_RETRIES", 1 if few else 0)
        calls = []
        results.append(cf.search_focal(run, first, scenes, nominal, scales, min_named=1))
        assert len(calls) == (1 if few else 3)
    one, ladder = results
    for got in (one, ladder):
        np.testing.assert_array_equal(np.asarray(got.ok), [True, True, True, True, True, False])
        np.testing.assert_array_equal(np.asarray(got.ids[1]), truth[1])  # 1.01 before 0.98
        np.testing.assert_array_equal(np.asarray(got.ids[3]), np.where(truth[3] >= 0, truth[3] + 1000, -1))
        assert np.asarray(got.attitude)[1, 0, 0] == pytest.approx(1.01)
        assert np.asarray(got.attitude)[3, 0, 0] == pytest.approx(0.98)
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(ladder), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _displaced(scenes, truth, nominal, keep, move, shift_px, tangential=False):
    """Names ``truth`` on the detections ``keep`` (B, N) bool only, with the detections ``move``
    pushed ``shift_px`` radially from the principal point (as a wrong focal length would) or
    across that direction."""
    xy = np.array(scenes.xy)
    centre = np.array([nominal.cx, nominal.cy])
    out = (xy - centre) / np.maximum(np.linalg.norm(xy - centre, axis=-1, keepdims=True), 1e-6)
    if tangential:
        out = np.stack([-out[..., 1], out[..., 0]], -1)
    xy = np.where(move[..., None], xy + shift_px * out, xy)
    return dataclasses.replace(scenes, xy=jnp.asarray(xy, jnp.float32)), np.where(keep, truth, -1)


def test_one_far_name_among_five_is_found_by_deletion(world):
    """Four names about 250 px from the centre and one at the edge 10 px off across the radial
    direction (a radial push is a scale change the other four cannot tell apart): a 4-parameter fit
    of five names bends to 1–2 px on every one of them; leaving each name out in turn finds it."""
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 0.98, n=24, seed=3)
    r = np.linalg.norm(np.asarray(scenes.xy) - [nominal.cx, nominal.cy], axis=-1)
    order = np.argsort(np.where(truth >= 0, np.abs(r - 250.0), np.inf), axis=1)
    far = np.argmax(np.where(truth >= 0, r, -1.0), axis=1)
    rows = np.arange(len(truth))
    keep, move = np.zeros(truth.shape, bool), np.zeros(truth.shape, bool)
    keep[rows[:, None], order[:, :4]] = True
    keep[rows, far] = move[rows, far] = True
    sign = np.where(rows % 2, 1.0, -1.0)[:, None, None]
    moved, names = _displaced(scenes, truth, nominal, keep, move, 10.0 * sign, tangential=True)
    kept, ok, _ = cf.verify_names(cat.unit_vectors, nominal, moved.xy, moved.valid, names,
                                  np.ones(len(names), bool))
    caught = np.asarray(kept)[move] == -1
    assert caught.sum() >= 20  # measured 21 of 24 (the former worst-name rule: 0)
    assert np.mean(np.asarray(ok)) >= 0.8  # … and the four others usually keep the scene


def test_two_wrong_names_on_one_side_do_not_widen_their_own_radius(world):
    """Two of twenty names at one edge 6 px off together: they pull a fit of every name and inflate
    its RMS; the refits from the better half, each name judged by the others' σ̂ and a trimmed σ̂,
    take both back in most scenes (a real scene adds the field check)."""
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 0.98, n=24, seed=4)
    x = np.where(truth >= 0, np.asarray(scenes.xy)[..., 0], np.inf)
    order = np.argsort(x, axis=1)
    rows = np.arange(len(truth))[:, None]
    keep = np.zeros(truth.shape, bool)
    keep[rows, order[:, :20]] = truth[rows, order[:, :20]] >= 0
    move = np.zeros(truth.shape, bool)
    move[rows, order[:, :2]] = True  # the two leftmost
    moved, names = _displaced(scenes, truth, nominal, keep, move, 6.0)
    kept, ok, fit = cf.verify_names(cat.unit_vectors, nominal, moved.xy, moved.valid, names,
                                    np.ones(len(names), bool))
    kept = np.asarray(kept)
    caught = np.all(kept[rows, order[:, :2]] == -1, axis=1)
    assert caught.sum() >= 14  # measured 16 of 24 (a plain RMS radius: 1)
    right = keep & ~move
    assert np.sum(kept[right] >= 0) >= 0.99 * right.sum()
    np.testing.assert_allclose(np.asarray(fit.scale)[np.asarray(ok) & caught], 0.98, atol=1e-3)


def test_a_right_sky_with_its_brightest_stars_missing_keeps_its_claim(world):
    """The field check asks only fits of a handful of names: a scene named in full whose five
    brightest stars were not detected stays solved with its many names (with the check on every
    fit it failed: the bright stars left unnamed are exactly the undetected ones), and fails the
    check once cut to a few names."""
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=24, seed=3)
    valid = np.array(scenes.valid)
    rows = np.arange(len(valid))
    mag = np.where(valid, np.asarray(scenes.mag), np.inf)
    for _ in range(5):  # the five brightest detections go missing
        valid[rows, np.argmin(mag, axis=1)] = False
        mag = np.where(valid, mag, np.inf)
    ids = np.where(valid, truth, -1)
    many = (ids >= 0).sum(1) > cf.FIELD_MAX_NAMES
    assert many.sum() >= 12
    kept, ok, _ = cf.verify_names(cat.unit_vectors, nominal, scenes.xy, valid, ids, np.ones(len(ids), bool))
    assert np.all(np.asarray(ok)[many])
    assert np.all((np.asarray(kept) < 0) | (np.asarray(kept) == truth))
    # the same scenes with only their six brightest remaining names: the field check fails most
    rank = np.argsort(np.argsort(mag, axis=1), axis=1)
    few = np.where(rank < 6, ids, -1)
    _, ok_few, _ = cf.verify_names(cat.unit_vectors, nominal, scenes.xy, valid, few, np.ones(len(ids), bool))
    assert np.asarray(ok_few)[many].mean() < 0.5


def _scipy_fit_distorted(xy, ref, cam):
    """Least squares over (rotation vector, scale, k1) of the pixel residuals, float64."""
    def residuals(p):
        v = Rotation.from_rotvec(p[:3]).apply(ref)
        u = v[:, :2] / v[:, 2:3]
        radial = 1.0 + p[4] * np.sum(u**2, 1, keepdims=True)
        pred = np.array([cam.cx, cam.cy]) + p[3] * cam.f_px * u * radial
        return (pred - xy).ravel()

    start = Rotation.align_vectors(np.asarray(cam.unproject(jnp.asarray(xy, jnp.float32)), np.float64),
                                   ref)[0].as_rotvec()
    return least_squares(residuals, np.r_[start, 1.0, 0.0], xtol=1e-12, ftol=1e-12).x


@pytest.mark.parametrize("k1", [-0.3, 0.4])
def test_fit_distorted_matches_scipy_least_squares(world, k1):
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.01, n=4)
    scenes = cf.distort_scenes(scenes, nominal, k1)
    for i in range(4):
        named = truth[i] >= 0
        xy = np.asarray(scenes.xy[i], np.float64)[named]
        ref = cat.unit_vectors[truth[i][named]]
        xy32, ref32 = jnp.asarray(xy, jnp.float32), jnp.asarray(ref, jnp.float32)
        ones = jnp.ones(len(xy), jnp.float32)
        c0, s0, _ = _fit_scaled(xy32, ref32, ones, nominal)
        c, s, k, resid, fitted = _fit_distorted(xy32, ref32, ones, nominal, start=(c0, s0))
        p = _scipy_fit_distorted(xy, ref, nominal)
        assert bool(fitted)
        assert abs(float(s) - p[3]) < 5e-5 and abs(float(k) - p[4]) < 5e-3, (float(s), float(k), p[3:])
        angle = np.linalg.norm((Rotation.from_matrix(np.asarray(c, np.float64))
                                * Rotation.from_rotvec(p[:3]).inv()).as_rotvec())
        assert np.degrees(angle) * 3600 < 1.0  # arcsec
        assert abs(p[3] - 1.01) < 2e-3 and abs(p[4] - k1) < 0.03  # the lens the scenes went through
        assert np.sqrt(np.mean(np.asarray(resid) ** 2)) < 1.5  # px: the noise alone (σ = 0.5 per axis)


def test_project_and_unproject_with_distortion_are_inverse(world):
    _, cam = world
    rng = np.random.default_rng(0)
    xy = jnp.asarray(rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (200, 2)), jnp.float32)
    for k1 in (-0.4, 0.0, 0.4):
        back, inside = cf.project_scaled(cam, cf.unproject_scaled(cam, xy, 1.01, k1), 1.01, k1)
        np.testing.assert_allclose(np.asarray(back), np.asarray(xy), atol=2e-3)
        assert np.all(np.asarray(inside))


def test_a_distorted_lens_keeps_its_edge_names_and_reports_k1(world):
    """With one radial term in the check's fit, the edge stars of a distorting lens are kept (the
    4-parameter fit takes them back as far off), none wrong, and the fitted k1 is the lens's."""
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=32)
    moved = cf.distort_scenes(scenes, nominal, 0.5)  # ≈ 20 px at the corners of this 20° frame
    ok = np.ones(len(truth), bool)
    kept_plain, _, _ = cf.verify_names(cat.unit_vectors, nominal, moved.xy, moved.valid, truth, ok,
                                       fit_distortion=False)
    kept, solved, fit = cf.verify_names(cat.unit_vectors, nominal, moved.xy, moved.valid, truth, ok)
    kept, kept_plain = np.asarray(kept), np.asarray(kept_plain)
    assert np.all(np.asarray(solved))
    assert np.all(kept[kept >= 0] == truth[kept >= 0])
    assert (kept >= 0).sum() == (truth >= 0).sum() > (kept_plain >= 0).sum()
    assert abs(np.median(np.asarray(fit.k1)) - 0.5) < 0.01
    # name_from_attitude names the rest of the frame through the fitted lens, no name wrong
    partial = truth.copy()
    partial[np.cumsum(truth >= 0, axis=1) > 14] = -1
    out = js.name_from_attitude(cat, nominal, moved, js.Identification(ids=partial, ok=ok))
    ids = np.asarray(out.ids)
    assert np.all(ids[ids >= 0] == truth[ids >= 0])
    assert (ids >= 0).sum() >= 0.97 * (truth >= 0).sum()
    k1 = np.asarray(out.distortion_k1)
    assert np.all(np.isfinite(k1)) and abs(np.median(k1) - 0.5) < 0.02


def test_sgm_camera_check_keeps_right_names_at_its_own_verification_cap(world):
    """At σ = 3 px (the SGM paper's largest noise) a right name 12 px off its star is within SGM's
    own verification cap (0.3°, 15.2 px on sgm2022): the camera check with SGM's cap keeps it,
    the default 10 px clip takes it back; a name from elsewhere in the sky goes either way."""
    from jstarid.algorithms import sgm
    from jstarid.algorithms.sgm.extensions import camera_check_cap_px

    cat, nominal = world
    cap = camera_check_cap_px(sgm.Config(), nominal)
    assert abs(cap - np.tan(np.radians(0.3)) * nominal.f_px) < 1e-3 and cap > cf.MAX_TOL_PX
    narrow = with_fields(sgm.Config(), {"verify.cap_deg": 0.1})  # 5 px: never below the default
    assert camera_check_cap_px(narrow, nominal) == cf.MAX_TOL_PX
    scenes, truth = _scenes(cat, nominal, 1.0, n=16, seed=3, sigma=3.0)
    named = truth >= 0
    assert np.all(named.sum(axis=1) >= 14)
    rows = np.arange(len(truth))
    slots = np.argsort(~named, axis=1, kind="stable")
    far, wrong = slots[:, 0], slots[:, 1]
    # the first name's detection moved 12 px along x from its star's noise-free spot
    ideal = js.simulate(jax.random.key(3), cat, nominal, js.NoiseConfig(position_sigma_px=0.0), batch_size=16)
    np.testing.assert_array_equal(np.asarray(ideal.truth), np.asarray(scenes.truth))
    xy = np.asarray(scenes.xy).copy()
    xy[rows, far] = np.asarray(ideal.xy)[rows, far] + np.array([12.0, 0.0], np.float32)
    moved = dataclasses.replace(scenes, xy=jnp.asarray(xy))
    ids = truth.copy()
    ids[rows, wrong] = (ids[rows, wrong] + 7) % len(cat)
    result = js.Identification(ids=jnp.asarray(ids), ok=jnp.ones(len(ids), bool))
    default = cf.check_identification(cat.unit_vectors, nominal, moved, result)
    wide = cf.check_identification(cat.unit_vectors, nominal, moved, result, max_tol_px=cap)
    studentized = cf.check_identification(cat.unit_vectors, nominal, moved, result, max_tol_px=cap,
                                          studentized=True)  # SGM's default
    for checked in (default, wide, studentized):
        kept = np.asarray(checked.ids)
        assert np.all(np.asarray(checked.ok))
        assert np.all(kept[rows, wrong] < 0)
        assert np.all((kept < 0) | (kept == truth))
    assert np.all(np.asarray(default.ids)[rows, far] < 0)
    assert np.all(np.asarray(wide.ids)[rows, far] == truth[rows, far])
    np.testing.assert_array_equal(np.asarray(studentized.ids), np.asarray(wide.ids))


def _named_in_centre_circle(cat, nominal, n, seed, sigma, radius_deg=6.0):
    """Scenes named (truth) within ``radius_deg`` of the boresight, as SGM names its neighbor
    circle: ``(scenes, ids)``."""
    scenes, truth = _scenes(cat, nominal, 1.0, n=n, seed=seed, sigma=sigma)
    body = np.asarray(nominal.unproject(scenes.xy))
    inside = np.degrees(np.arccos(np.clip(body[..., 2], -1.0, 1.0))) < radius_deg
    return scenes, np.where(inside, truth, -1)


def test_noise_estimate_of_a_dozen_names_keeps_every_right_name(world):
    """σ = 1.5 px, each scene named in a 6° circle about the centre (≈ 12 names, as SGM names its
    neighbor circle): the refits' σ̂ must not shrink onto the better half of the names. It did, to
    0.56 px in one of these scenes (a fixed point at the 2.5 px floor), and took right names 3–5 px
    out back; its lower bound, the trimmed σ̂ over every name, keeps them all."""
    cat, nominal = world
    sigma = 1.5
    scenes, ids = _named_in_centre_circle(cat, nominal, n=256, seed=5, sigma=sigma)
    dozen = (ids >= 0).sum(axis=1) >= 11
    assert dozen.sum() >= 100
    kept, ok, fit = cf.verify_names(cat.unit_vectors, nominal, scenes.xy, scenes.valid, ids,
                                    np.ones(len(ids), bool))
    kept = np.asarray(kept)[dozen]
    assert np.all(np.asarray(ok)[dozen])
    np.testing.assert_array_equal(kept, ids[dozen])  # every right name kept
    assert np.min(np.asarray(fit.sigma_px)[dozen]) > 0.6 * sigma


@pytest.mark.parametrize("dof", [1, 4, 16, 26, 100, 10_000])
def test_studentized_radius_has_the_tail_of_a_known_sigma(dof):
    """r² / (2 σ̂²) of a right name is F(2, dof): the studentized radius leaves it the tail
    exp(−k²/2) that k σ leaves a known σ (SciPy's F distribution as the reference)."""
    from scipy.stats import f

    k = 6.0
    radius = float(cf.studentized_k(k, dof))
    np.testing.assert_allclose(f.sf(radius**2 / 2.0, 2, dof), np.exp(-k**2 / 2.0), rtol=1e-3)
    assert radius >= k


@pytest.mark.slow
def test_studentized_check_keeps_the_right_names_the_plain_radius_takes_back(world):
    """σ = 1 px, each scene named in a 6° circle (≈ 12 names, SGM's): 6 σ̂ of a dozen names takes
    right names 3–4 px out back (σ̂ scatters by about 15 %, 1 / √(2 dof)), the studentized radius
    keeps every one, and a name twice SGM's cap from its star is still taken back. (At 20 px, one
    of 9–10 names bends the fit to σ̂ ≈ 4.4 px and stayed in 2 of 1,824 such scenes, with either
    radius.)"""
    from jstarid.algorithms import sgm
    from jstarid.algorithms.sgm.extensions import camera_check_cap_px

    cat, nominal = world
    scenes, ids = _named_in_centre_circle(cat, nominal, n=1024, seed=9, sigma=1.0)
    rows = np.flatnonzero((ids >= 0).sum(axis=1) >= 8)
    ids, xy, valid = ids[rows], np.asarray(scenes.xy)[rows], np.asarray(scenes.valid)[rows]
    claimed = np.ones(len(rows), bool)
    cap = camera_check_cap_px(sgm.Config(), nominal)  # 15.2 px on sgm2022
    plain, _, _ = cf.verify_names(cat.unit_vectors, nominal, xy, valid, ids, claimed, max_tol_px=cap)
    kept, ok, _ = cf.verify_names(cat.unit_vectors, nominal, xy, valid, ids, claimed, max_tol_px=cap,
                                  studentized=True)
    assert np.sum((np.asarray(plain) < 0) & (ids >= 0)) > 0  # the plain radius takes right names back
    np.testing.assert_array_equal(np.asarray(kept), ids)  # the studentized one keeps them all
    assert np.all(np.asarray(ok))
    # one name per scene moved twice the cap off its star: taken back, the rest kept
    moved = xy.copy()
    first = np.argmax(ids >= 0, axis=1)
    moved[np.arange(len(rows)), first, 0] += 2 * cap
    kept, ok, _ = cf.verify_names(cat.unit_vectors, nominal, moved, valid, ids, claimed, max_tol_px=cap,
                                  studentized=True)
    kept = np.asarray(kept)
    assert np.all(np.asarray(ok))
    assert np.all(kept[np.arange(len(rows)), first] == -1)
    others = ids.copy()
    others[np.arange(len(rows)), first] = -1
    np.testing.assert_array_equal(kept, others)


def test_a_false_detection_beside_a_named_star_loses_the_name(world):
    """Six names, one of them on a false detection 4 px from its star, whose own detection is
    there but unnamed (an algorithm that votes with its brightest detections never saw it): the
    fit bends towards the false one, yet the star then has a second detection within the radius,
    so that name is taken back and the five right ones stay."""
    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=16, seed=5)
    # one more column for the false detection
    xy = np.concatenate([np.array(scenes.xy), np.zeros((len(truth), 1, 2), np.float32)], axis=1)
    valid = np.concatenate([np.array(scenes.valid), np.zeros((len(truth), 1), bool)], axis=1)
    truth = np.concatenate([truth, np.full((len(truth), 1), -1)], axis=1)
    rows, spare = np.arange(len(truth)), truth.shape[1] - 1
    six = np.argsort(np.where(truth >= 0, np.arange(truth.shape[1]), 10**6), axis=1)[:, :6]
    star = six[:, 0]
    angle = np.random.default_rng(0).uniform(0, 2 * np.pi, len(rows))
    xy[rows, spare] = xy[rows, star] + 4.0 * np.stack([np.cos(angle), np.sin(angle)], -1)
    valid[rows, spare] = True
    names = np.full(truth.shape, -1)
    names[rows[:, None], six[:, 1:]] = truth[rows[:, None], six[:, 1:]]
    names[rows, spare] = truth[rows, star]  # the false detection named as the star; the star unnamed
    kept, ok, fit = cf.verify_names(cat.unit_vectors, nominal, jnp.asarray(xy, jnp.float32), valid, names,
                                    np.ones(len(rows), bool))
    kept = np.asarray(kept)
    assert (kept[rows, spare] == -1).all()
    # the right names mostly stay: the bent fit's radius (6–9 px) can hold another detection
    right = kept[rows[:, None], six[:, 1:]] == names[rows[:, None], six[:, 1:]]
    assert np.asarray(ok).all() and right.mean() >= 0.9  # measured 77 of 80
    assert ((kept == truth) | (kept == -1)).all()  # no wrong name anywhere
    # the same scenes without the false detection, named right: every name stays
    names_right = np.full(truth.shape, -1)
    names_right[rows[:, None], six] = truth[rows[:, None], six]
    clean = valid.copy()
    clean[:, spare] = False
    kept_right, ok_right, _ = cf.verify_names(cat.unit_vectors, nominal, jnp.asarray(xy, jnp.float32), clean,
                                              names_right, np.ones(len(rows), bool))
    assert np.asarray(ok_right).all() and (np.asarray(kept_right) == names_right).all()
    # the kernel against a plain projection through the fitted camera, on the names given (the
    # false one among them: rivalled by the star's own detection, which is unnamed; a named
    # detection nearer its own star is no rival)
    own = np.argsort(names < 0, axis=1, kind="stable")[:, :6].astype(np.int32)  # the six names' columns
    theirs = names >= 0
    their_ref = cat.unit_vectors[np.maximum(names, 0)]
    got = np.asarray(cf._rival_kernel(
        jnp.asarray(cat.unit_vectors[np.take_along_axis(names, own, axis=1)], jnp.float32),
        jnp.ones(own.shape, bool), jnp.asarray(own), jnp.asarray(xy, jnp.float32), jnp.asarray(valid),
        jnp.asarray(their_ref, jnp.float32), jnp.asarray(theirs),
        fit.attitude, fit.scale, fit.k1, fit.tol_px, nominal.pinhole_numbers()))
    for b in rows:
        cam = dataclasses.replace(nominal, f_px=nominal.f_px * float(fit.scale[b]))
        att = np.asarray(fit.attitude[b], np.float64)
        p = np.asarray(cam.project(jnp.asarray(cat.unit_vectors[names[b, own[b]]] @ att.T, jnp.float32))[0])
        d = np.linalg.norm(xy[b][None, :, :] - p[:, None, :], axis=-1)  # (6, N) px
        q = np.asarray(cam.project(jnp.asarray(their_ref[b] @ att.T, jnp.float32))[0])  # (N, 2)
        d_theirs = np.linalg.norm(xy[b] - q, axis=-1)  # (N,) px from its own star
        explained = theirs[b][None, :] & (d_theirs[None, :] < d)
        others = valid[b][None, :] & (np.arange(xy.shape[1])[None, :] != own[b][:, None]) & ~explained
        want = (others & (d <= float(fit.tol_px[b]))).any(axis=1)
        np.testing.assert_array_equal(got[b], want)
    assert got[rows, np.argmax(own == spare, axis=1)].all()  # the false name: always rivalled


def test_a_named_neighbour_within_the_radius_is_no_rival():
    """Eight right names (a fit of at most ten), two of them a close pair 2 px apart, inside the
    check's radius (never below 2.5 px): both stay, because each one's neighbour is named and nearer
    its own star. Without that exemption the kernel takes both back (SGM names every star of its
    circle, and lost right names this way)."""
    cam = js.camera_preset("sgm2022")
    rng = np.random.default_rng(11)
    pix = rng.uniform(100, 900, (8, 2))
    pix[7] = pix[0] + np.array([2.0, 0.0])  # the close pair: stars 0 and 7
    stars = np.asarray(cam.unproject(jnp.asarray(pix, jnp.float32)), np.float64)  # attitude: identity
    turn = rng.uniform(0, 2 * np.pi, 8)
    xy = (pix + 0.2 * np.stack([np.cos(turn), np.sin(turn)], 1)).astype(np.float32)[None]
    valid = np.ones((1, 8), bool)
    ids = np.arange(8, dtype=np.int32)[None]
    kept, ok, fit = cf.verify_names(stars, cam, jnp.asarray(xy), valid, ids, np.ones(1, bool))
    assert bool(ok[0]) and (np.asarray(kept) == ids).all()
    ref = jnp.asarray(stars[ids], jnp.float32)
    args = (ref, jnp.ones((1, 8), bool), jnp.asarray(ids), jnp.asarray(xy), jnp.asarray(valid), ref)
    fitted = (fit.attitude, fit.scale, fit.k1, fit.tol_px, cam.pinhole_numbers())
    with_exemption = np.asarray(cf._rival_kernel(*args, jnp.ones((1, 8), bool), *fitted))
    without = np.asarray(cf._rival_kernel(*args, jnp.zeros((1, 8), bool), *fitted))
    assert not with_exemption.any()
    np.testing.assert_array_equal(without[0], np.isin(np.arange(8), [0, 7]))


def test_small_batches_share_the_checks_programs(world):
    """A call of the check's smallest size keeps every detection column: a scene of six names (the
    few-names checks: rival detections, the field) cut to its 20 and to its 40 brightest
    detections runs the same programs (each new width compiled the kernels
    again), and the width changes no name."""
    from jstarid.runtime import CountCompilations

    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=1, seed=3)
    valid = np.array(scenes.valid)
    assert valid[0, :40].all()
    ids = np.where(np.cumsum(truth >= 0, axis=1) <= 6, truth, -1)
    assert np.sum(ids >= 0) == 6
    claim = js.Identification(ids=jnp.asarray(ids), ok=jnp.ones(1, bool))
    # the scene's 20 brightest detections, then its 40 brightest (the same six named)
    narrow = dataclasses.replace(scenes, valid=jnp.asarray(valid & (np.arange(valid.shape[1]) < 20)))
    wide = dataclasses.replace(scenes, valid=jnp.asarray(valid & (np.arange(valid.shape[1]) < 40)))
    first = cf.check_identification(cat.unit_vectors, nominal, narrow, claim)
    with CountCompilations() as count:
        second = cf.check_identification(cat.unit_vectors, nominal, wide, claim)
    assert count.programs == 0
    assert bool(first.ok[0]) and bool(second.ok[0])
    np.testing.assert_array_equal(np.asarray(second.ids), np.asarray(first.ids))


def test_the_studentized_radius_shares_the_plain_radius_programs(world):
    """``studentized`` (SGM's check) is a traced flag of the fit kernel: the check with it and without
    it runs the same programs, and it still widens the radius (a dozen names: 6 σ̂ → ≈ 10 σ̂)."""
    from jstarid.runtime import CountCompilations

    cat, nominal = world
    scenes, truth = _scenes(cat, nominal, 1.0, n=2, seed=5)
    ids = np.where(np.cumsum(truth >= 0, axis=1) <= 12, truth, -1)
    assert np.all(np.sum(ids >= 0, axis=1) == 12)
    args = (cat.unit_vectors, nominal, scenes.xy, scenes.valid, ids, np.ones(2, bool))
    plain = cf.verify_names(*args, max_tol_px=100.0)[2]
    with CountCompilations() as count:
        wide = cf.verify_names(*args, max_tol_px=100.0, studentized=True)[2]
    assert count.programs == 0
    ratio = np.asarray(wide.tol_px) / np.asarray(plain.tol_px)
    assert np.all(ratio > 1.3), ratio
