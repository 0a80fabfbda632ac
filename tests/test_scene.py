import numpy as np
import pytest

import jstarid as js


def test_scenes_from_centroids_sorts_and_pads():
    xy = [np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]]), np.zeros((0, 2))]
    mag = [np.array([5.0, 2.0, 3.0]), None]
    s = js.scenes_from_centroids(xy, mag, capacity=4)
    assert s.xy.shape == (2, 4, 2)
    np.testing.assert_array_equal(np.asarray(s.valid), [[1, 1, 1, 0], [0, 0, 0, 0]])
    np.testing.assert_allclose(np.asarray(s.xy[0, :3]), [[30, 40], [50, 60], [10, 20]])
    np.testing.assert_allclose(np.asarray(s.mag[0, :3]), [2, 3, 5])
    assert bool(np.all(np.asarray(s.truth) == -1))
    assert bool(np.all(np.isnan(np.asarray(s.attitude))))
    assert not bool(s.overflow.any())


def test_scenes_from_centroids_overflow_keeps_brightest():
    xy = [np.arange(20.0).reshape(10, 2)]
    mag = [np.arange(10.0)[::-1]]
    s = js.scenes_from_centroids(xy, mag, capacity=3)
    assert bool(s.overflow[0])
    np.testing.assert_allclose(np.asarray(s.mag[0]), [0, 1, 2])


def test_scenes_from_centroids_bad_input():
    with pytest.raises(ValueError, match="NaN"):
        js.scenes_from_centroids([np.array([[1.0, np.nan]])])
    with pytest.raises(ValueError, match="magnitudes"):
        js.scenes_from_centroids([np.ones((2, 2))], [np.ones(3)])
    with pytest.raises(ValueError, match="capacity"):
        js.scenes_from_centroids([np.ones((2, 2))], capacity=0)
    with pytest.raises(ValueError, match="NaN or inf"):
        js.scenes_from_centroids([np.ones((1, 2))], [np.array([np.inf])])
    # shapes that a reshape(-1, 2) would silently misread
    with pytest.raises(ValueError, match=r"for one scene pass \[xy\]"):
        js.scenes_from_centroids(np.ones((5, 2)))  # a bare array is not five one-star scenes
    with pytest.raises(ValueError, match=r"\(n, 2\) array"):
        js.scenes_from_centroids([np.ones((2, 5))])  # transposed
    with pytest.raises(ValueError, match=r"\(n, 2\) array"):
        js.scenes_from_centroids([np.ones((5, 3))])  # x, y, flux
    with pytest.raises(ValueError, match="capacity"):
        js.scenes_from_centroids([np.ones((2, 2))], capacity=8.0)
    assert js.scenes_from_centroids(np.ones((3, 5, 2))).batch_size == 3  # a (B, n, 2) array is fine


def test_scene_indexing_keeps_batch_axis():
    s = js.scenes_from_centroids([np.ones((2, 2)), np.ones((1, 2))], capacity=4)
    one = s[1]
    assert one.xy.shape == (1, 4, 2)
    assert int(one.n_stars[0]) == 1


def test_pad_with_empty_adds_scenes_without_detections():
    scenes = js.scenes_from_centroids([np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([[5.0, 6.0]])],
                                      capacity=3)
    padded = js.pad_with_empty(scenes, 5)
    assert padded.batch_size == 5 and padded.capacity == 3
    np.testing.assert_array_equal(np.asarray(padded.xy[:2]), np.asarray(scenes.xy))
    np.testing.assert_array_equal(np.asarray(padded.valid[:2]), np.asarray(scenes.valid))
    assert not np.asarray(padded.valid[2:]).any()
    assert np.all(np.asarray(padded.mag[2:]) == np.inf) and np.all(np.asarray(padded.truth[2:]) == -1)
    assert np.all(np.isnan(np.asarray(padded.attitude[2:])))
    assert js.pad_with_empty(scenes, 2) is scenes
    with pytest.raises(ValueError, match="cannot pad"):
        js.pad_with_empty(scenes, 1)


def test_gathering_and_padding_sub_batches_compile_nothing():
    """The host loops pick sub-batches of every length: rows gathered by an index array or a mask,
    and empty scenes padded on, are the rows NumPy indexing gives, as device arrays, and no row count
    compiles a program (an eager device gather or concatenation compiles one per new shape)."""
    import jax

    xy = [np.arange(2 * k, dtype=float).reshape(k, 2) + 10 * k for k in range(1, 10)]
    scenes = js.scenes_from_centroids(xy, None, capacity=8)
    ids = js.Identification(ids=jax.device_put(np.arange(72, dtype=np.int32).reshape(9, 8)),
                            ok=jax.device_put(np.arange(9) % 2 == 0))
    scenes[np.array([0, 1])], js.pad_with_empty(scenes[np.array([0])], 2)  # warm the indexing path
    with js.runtime.CountCompilations() as count:
        for rows in ([3], [1, 4, 2], [0, 2, 4, 6, 8], np.arange(9) % 3 == 0):
            sub, result = scenes[np.asarray(rows)], ids[np.asarray(rows)]
            assert isinstance(sub.xy, jax.Array) and isinstance(result.ids, jax.Array)
            np.testing.assert_array_equal(np.asarray(sub.xy), np.asarray(scenes.xy)[np.asarray(rows)])
            np.testing.assert_array_equal(np.asarray(result.ok), np.asarray(ids.ok)[np.asarray(rows)])
            padded = js.pad_with_empty(sub, sub.batch_size + 3)
            assert padded.batch_size == sub.batch_size + 3 and not np.asarray(padded.valid)[-3:].any()
        # slices and ints too: an eager slice of a device array compiled a program per length
        for index in (slice(0, 2), slice(None, 5), slice(3, None), slice(1, 8, 3), 4):
            sub, result = scenes[index], ids[index]
            want = slice(index, index + 1) if isinstance(index, int) else index
            assert isinstance(sub.xy, jax.Array) and isinstance(result.ids, jax.Array)
            np.testing.assert_array_equal(np.asarray(sub.xy), np.asarray(scenes.xy)[want])
            np.testing.assert_array_equal(np.asarray(result.ids), np.asarray(ids.ids)[want])
    assert count.programs == 0
    # inside a trace the gather is part of the program
    traced = jax.jit(lambda s, r: s[r].xy)(scenes, np.array([2, 5]))
    np.testing.assert_array_equal(np.asarray(traced), np.asarray(scenes.xy)[[2, 5]])


def test_with_rows_replaces_those_scenes_and_fills_what_was_missing():
    base = js.Identification(ids=np.arange(12, dtype=np.int32).reshape(4, 3), ok=np.array([1, 0, 1, 0], bool),
                             attitude=None, focal_scale=np.ones(4, np.float32))
    part = js.Identification(ids=np.full((2, 3), 7, np.int32), ok=np.ones(2, bool),
                             attitude=np.tile(np.eye(3, dtype=np.float32), (2, 1, 1)), focal_scale=None)
    out = base.with_rows(np.array([3, 1]), part)
    np.testing.assert_array_equal(np.asarray(out.ids), [[0, 1, 2], [7, 7, 7], [6, 7, 8], [7, 7, 7]])
    np.testing.assert_array_equal(np.asarray(out.ok), [True, True, True, True])
    att = np.asarray(out.attitude)  # missing before: NaN except the rows given
    assert np.isnan(att[[0, 2]]).all() and np.array_equal(att[[1, 3]], part.attitude)
    np.testing.assert_array_equal(np.asarray(out.focal_scale), np.ones(4))  # part had none: kept
    assert out.distortion_k1 is None
