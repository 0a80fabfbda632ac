"""name_from_attitude (jstarid.completion) against a NumPy/SciPy reference and the truth."""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid.completion import first_argmax, magnitude_agrees, name_from_attitude, name_stars


def reference(cat, cam, xy, valid, ids, ok, tol_px, iso, min_named):
    """The module's rule over the whole catalog, attitude by SciPy's align_vectors, float64."""
    out = ids.copy()
    tol = tol_px / cam.f_px
    for b in range(len(ids)):
        named = valid[b] & (ids[b] >= 0)
        if not ok[b] or named.sum() < min_named:
            continue
        body = np.asarray(cam.unproject(xy[b]), np.float64)
        rot, _ = Rotation.align_vectors(body[named], cat.unit_vectors[ids[b][named]])
        sky = rot.inv().apply(body)  # each detection's ICRS direction
        cross = np.linalg.norm(np.cross(sky[:, None], cat.unit_vectors[None]), axis=-1)
        ang = np.arctan2(cross, sky @ cat.unit_vectors.T)  # (N, M) rad
        order = np.argsort(ang, axis=1)[:, :2]
        d1 = np.take_along_axis(ang, order[:, :1], 1)[:, 0]
        d2 = np.take_along_axis(ang, order[:, 1:], 1)[:, 0]
        cand = valid[b] & (d1 <= tol) & (d2 > iso * tol)
        best = order[:, 0]
        clash = np.array([cand[j] and np.sum(cand & (best == best[j])) > 1 for j in range(len(best))])
        new = cand & ~clash & (ids[b] < 0) & ~np.isin(best, ids[b][named])
        out[b, new] = best[new]
    return out


@pytest.fixture(scope="module")
def setup():
    cat = js.load_catalog(6.0)
    cam = js.camera_preset("rpnet2019")
    noise = js.NoiseConfig(position_sigma_px=0.3, n_false=3)
    scenes = js.simulate(jax.random.key(7), cat, cam, noise, batch_size=48, capacity=48)
    truth = np.where(np.asarray(scenes.valid), np.asarray(scenes.truth), -1)
    # an algorithm that named only the first 4 catalog stars of each scene (like MLV's brightest N)
    partial = truth.copy()
    partial[np.cumsum(truth >= 0, axis=1) > 4] = -1
    ok = np.ones(len(truth), bool)
    ok[:3] = False  # failed scenes stay failed
    return cat, cam, scenes, truth, partial, ok


# the naming rule alone (nominal camera, the radius at tol_px, no brightness check): the reference
PLAIN = dict(fit_scale=False, k_sigma=math.inf, mag_tol=math.inf)


def test_matches_reference_and_truth(setup):
    cat, cam, scenes, truth, partial, ok = setup
    result = js.Identification(ids=partial, ok=ok)
    out = name_from_attitude(cat, cam, scenes, result, **PLAIN)
    ids = np.asarray(out.ids)
    ref = reference(cat, cam, np.asarray(scenes.xy, np.float64), np.asarray(scenes.valid), partial, ok,
                    2.0, 2.0, 3)
    np.testing.assert_array_equal(ids, ref)
    named = ids >= 0
    assert np.all(ids[named] == truth[named])  # no wrong name, false stars unnamed
    assert np.all(ids[:3] == partial[:3])  # failed scenes untouched
    # nearly every catalog star of the solved scenes is named (a few close pairs stay unnamed)
    assert named[3:].sum() >= 0.95 * (truth[3:] >= 0).sum()
    assert named[3:].sum() > 2 * (partial[3:] >= 0).sum()
    # the refitted attitude is the true one to a few arcseconds
    err = np.asarray(js.attitude_errors_arcsec(out.attitude[3:], scenes.attitude[3:])[0])
    assert np.all(err < 20)


def test_naming_rounds_run_in_calls_of_a_few_sizes(setup):
    """Only the solved scenes are named, in calls of power-of-two sizes: 5 and 6 scenes meet the same
    programs (their 48 columns are below the smallest cut, ``EXTEND_MIN_WIDTH``), and each scene's
    names are those it gets in the whole batch."""
    from jstarid import completion

    cat, cam, scenes, truth, partial, ok = setup

    def name(rows):
        return np.asarray(name_from_attitude(cat, cam, scenes[rows], js.Identification(
            ids=partial[rows], ok=ok[rows]), **PLAIN).ids)

    whole = name(slice(0, 48))
    np.testing.assert_array_equal(name(slice(3, 8)), whole[3:8])
    programs = completion._extend._cache_size()
    np.testing.assert_array_equal(name(slice(8, 14)), whole[8:14])
    assert completion._extend._cache_size() == programs


def test_columns_past_the_detections_change_no_name(setup):
    """The naming rounds cut each call to the columns its scenes fill: the same scenes padded to the
    naming capacity (512 columns, as frames read from files are) get the same names, with the scale
    scan on (the default)."""
    from jstarid import completion

    cat, cam, scenes, truth, partial, ok = setup
    rows = slice(0, 8)
    narrow = name_from_attitude(cat, cam, scenes[rows], js.Identification(ids=partial[rows], ok=ok[rows]))
    wide_n = 512
    assert completion.EXTEND_MIN_WIDTH < wide_n

    def widen(a, fill):
        a = np.asarray(a)
        pad = np.full((a.shape[0], wide_n - a.shape[1], *a.shape[2:]), fill, a.dtype)
        return np.concatenate([a, pad], axis=1)

    part = scenes[rows]
    wide = dataclasses.replace(part, xy=widen(part.xy, 0.0), mag=widen(part.mag, np.inf),
                               truth=widen(part.truth, -1), valid=widen(part.valid, False))
    out = name_from_attitude(cat, cam, wide, js.Identification(ids=widen(partial[rows], -1), ok=ok[rows]))
    ids = np.asarray(out.ids)
    np.testing.assert_array_equal(ids[:, :48], np.asarray(narrow.ids))
    assert np.all(ids[:, 48:] == -1)
    np.testing.assert_array_equal(np.asarray(out.ok), np.asarray(narrow.ok))
    named = ids[3:, :48] >= 0  # the solved scenes: nearly every star named, none wrongly
    assert named.sum() >= 0.9 * (truth[3:8] >= 0).sum()
    assert np.all(ids[3:, :48][named] == truth[3:8][named])


def test_too_few_names_and_conflicts_are_left_alone(setup):
    cat, cam, scenes, truth, partial, ok = setup
    two = truth.copy()
    two[np.cumsum(truth >= 0, axis=1) > 2] = -1  # 2 names < min_named = 3
    out = name_from_attitude(cat, cam, scenes, js.Identification(ids=two, ok=np.ones(len(two), bool)))
    np.testing.assert_array_equal(np.asarray(out.ids), two)
    # a wrong name among the given ones: the second star's name put on the first star's detection
    b = 5
    first, second = np.nonzero(truth[b] >= 0)[0][:2]
    for keep, solved in ((4, False), (8, True)):
        clash = truth.copy()
        clash[np.cumsum(truth >= 0, axis=1) > keep] = -1
        clash[b, first] = truth[b, second]
        clash[b, second] = -1
        out = name_from_attitude(cat, cam, scenes, js.Identification(ids=clash, ok=ok),
                                 fit_scale=False)
        ids = np.asarray(out.ids)
        assert bool(out.ok[b]) == solved
        if solved:  # the camera fit takes the wrong name back; each star is named once, rightly
            assert ids[b, first] == truth[b, first] and ids[b, second] == truth[b, second]
            assert np.sum(ids[b] == truth[b, second]) == 1
        else:  # 2 right names and a wrong one: too few to trust, the scene fails, nothing wrong
            assert np.all(ids[b] == -1)


def test_bad_arguments(setup):
    cat, cam, scenes, truth, partial, ok = setup
    result = js.Identification(ids=partial, ok=ok)
    for kwargs in ({"tol_px": 0.0}, {"tol_px": np.nan}, {"isolation": 0.5}, {"min_named": 1}):
        with pytest.raises(ValueError):
            name_from_attitude(cat, cam, scenes, result, **kwargs)


def test_first_argmax_matches_argmax():
    rng = np.random.default_rng(3)
    x = rng.integers(0, 4, size=(50, 17)).astype(np.float32)  # many ties
    np.testing.assert_array_equal(np.asarray(first_argmax(jnp.asarray(x))), np.argmax(x, -1))
    inf = np.full((2, 5), np.inf, np.float32)
    np.testing.assert_array_equal(np.asarray(first_argmax(-jnp.asarray(inf))), [0, 0])


def test_name_stars():
    rng = np.random.default_rng(0)
    cos_t = rng.uniform(math.cos(math.radians(10.0)), 1.0, 50)  # 50 stars within 10° of +z
    phi = rng.uniform(0, 2 * np.pi, 50)
    stars = np.stack([np.sqrt(1 - cos_t**2) * np.cos(phi), np.sqrt(1 - cos_t**2) * np.sin(phi), cos_t], -1)
    c = np.asarray(js.random_rotation(jax.random.key(2)), np.float64)
    rows = np.array([3, 10, 20, 30, 3])  # the last detection duplicates row 3: both must be dropped
    body = (stars[rows] @ c.T).astype(np.float32)
    body[1] = body[1] + np.array([1e-3, 0, 0], np.float32)  # ≈ 0.06°: outside a 0.01° tolerance
    valid = np.array([True, True, True, False, True])
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
    got, named = name_stars(f32(c), f32(body), jnp.asarray(valid), f32(stars), math.radians(0.01))
    np.testing.assert_array_equal(np.asarray(named), [False, False, True, False, False])
    assert int(got[2]) == 20
    # isolation: the second-nearest star of detection 2, at angle a, blocks the name once
    # isolation · tol reaches it
    sep = np.degrees(np.arccos(np.clip(stars @ stars[20], -1, 1)))
    a = np.sort(sep)[1]
    for iso, expect in ((0.9 * a / 0.01, True), (1.1 * a / 0.01, False)):
        _, named = name_stars(f32(c), f32(body), jnp.asarray(valid), f32(stars), math.radians(0.01),
                              max(iso, 1.0))
        assert bool(named[2]) == expect


def test_a_saturated_bright_star_may_read_fainter_but_never_far_brighter():
    """The brightness check of new names: a star brighter than the named stars' median V may read
    fainter by up to that difference (saturation); on the bright side, and for a faint star, the
    plain tolerance holds."""
    star = jnp.array([4.0, 4.5, 5.0, 5.5, 6.0, 6.5, 0.9, 0.9, 7.5, 5.5])  # V of each detection's star
    det = star + 2.0  # instrumental zero point 2 mag
    det = det.at[6].add(1.3)  # Spica read 1.3 mag fainter: saturated
    det = det.at[7].add(-1.3)  # … 1.3 mag brighter: another object
    det = det.at[8].add(1.3)  # a V 7.5 star 1.3 mag fainter: no saturation there
    det = det.at[9].add(0.8)  # within the plain tolerance
    named = jnp.arange(10) < 6
    candidate = ~named
    got = np.asarray(magnitude_agrees(det, star, named, candidate, 1.0))
    np.testing.assert_array_equal(got, [False] * 6 + [True, False, False, True])
