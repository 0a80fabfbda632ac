"""name_from_attitude (jstarid.completion) against a NumPy/SciPy reference and the truth."""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid.completion import name_from_attitude


def reference(cat, cam, xy, valid, ids, ok, tol, iso, min_named):
    """The module's three conditions over the whole catalog, attitude by SciPy's align_vectors."""
    out = ids.copy()
    for b in range(len(ids)):
        named = valid[b] & (ids[b] >= 0)
        if not ok[b] or named.sum() < min_named:
            continue
        body = np.asarray(cam.unproject(xy[b][named]), np.float64)
        rot, _ = Rotation.align_vectors(body, cat.unit_vectors[ids[b][named]])
        v = rot.apply(cat.unit_vectors)
        front = np.nonzero(v[:, 2] > 0)[0]
        px = np.stack([cam.cx + cam.f_px * v[front, 0] / v[front, 2],
                       cam.cy + cam.f_px * v[front, 1] / v[front, 2]], -1)
        d = np.linalg.norm(xy[b][:, None] - px[None], axis=-1)
        d[~valid[b]] = np.inf
        for j in np.nonzero(valid[b] & (ids[b] < 0))[0]:
            order = np.argsort(d[j])
            k = order[0]
            if d[j, k] > tol or d[j, order[1]] <= iso * tol:
                continue
            if np.argmin(d[:, k]) != j or front[k] in ids[b]:
                continue
            out[b, j] = front[k]
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


def test_matches_reference_and_truth(setup):
    cat, cam, scenes, truth, partial, ok = setup
    result = js.Identification(ids=partial, ok=ok)
    out = name_from_attitude(cat, cam, scenes, result)
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


def test_too_few_names_and_conflicts_are_left_alone(setup):
    cat, cam, scenes, truth, partial, ok = setup
    two = truth.copy()
    two[np.cumsum(truth >= 0, axis=1) > 2] = -1  # 2 names < min_named = 3
    out = name_from_attitude(cat, cam, scenes, js.Identification(ids=two, ok=np.ones(len(two), bool)))
    np.testing.assert_array_equal(np.asarray(out.ids), two)
    # a star already named elsewhere is not given twice: name the first star's detection after the
    # second star, then the second star's own detection must stay unnamed
    clash = partial.copy()
    b = 5
    first, second = np.nonzero(truth[b] >= 0)[0][:2]
    clash[b, first] = truth[b, second]
    clash[b, second] = -1
    out = np.asarray(name_from_attitude(cat, cam, scenes, js.Identification(ids=clash, ok=ok)).ids)
    assert out[b, second] == -1 and np.sum(out[b] == truth[b, second]) == 1


def test_bad_arguments(setup):
    cat, cam, scenes, truth, partial, ok = setup
    result = js.Identification(ids=partial, ok=ok)
    for kwargs in ({"tol_px": 0.0}, {"tol_px": np.nan}, {"isolation": 0.5}, {"min_named": 1}):
        with pytest.raises(ValueError):
            name_from_attitude(cat, cam, scenes, result, **kwargs)
