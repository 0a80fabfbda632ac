"""Names a neighbouring catalog star explains as well (jstarid.rival_stars, the finishing stage's step 2b)."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid import rival_stars
from jstarid.finishing import Finishing, StarTable, finish
from jstarid.sky_index import build_sky_index

CAMERA = js.camera_preset("sgm2022")
SIGMA_PX = 1.5  # centroid noise of the synthetic frames (px per axis)
ZERO_POINT = 1.7  # instrumental magnitude − V


def _sky(xy, attitude, scale=1.0):
    """(n, 2) px → (n, 3) ICRS unit vectors through the pinhole of focal length ``scale · f_px``."""
    f = CAMERA.f_px * scale
    ray = np.stack([(xy[:, 0] - CAMERA.cx) / f, (xy[:, 1] - CAMERA.cy) / f, np.ones(len(xy))], 1)
    return (ray / np.linalg.norm(ray, axis=1, keepdims=True)) @ attitude  # r = Cᵀ v


def _frame(rng, n_stars=40, n_pairs=15, scale=1.0, error_px=None):
    """A synthetic frame: stars at random pixels (a close neighbour 3–10 px from ``n_pairs`` of
    them), each of the first ``n_stars`` detected with SIGMA_PX noise (or exactly ``error_px`` off,
    in a random direction); true attitude and the table."""
    attitude = Rotation.random(random_state=rng).as_matrix()  # C: ICRS → camera
    xy = rng.uniform([40, 40], [CAMERA.width - 40, CAMERA.height - 40], (n_stars, 2))
    angle = rng.uniform(0, 2 * np.pi, n_pairs)
    apart = rng.uniform(3, 10, n_pairs)[:, None]
    pair_xy = xy[:n_pairs] + apart * np.stack([np.cos(angle), np.sin(angle)], 1)
    vectors = _sky(np.concatenate([xy, pair_xy]), attitude, scale)
    mags = rng.uniform(3.0, 6.0, len(vectors))
    if error_px is None:
        det_xy = xy + rng.normal(0, SIGMA_PX, xy.shape)
    else:
        turn = rng.uniform(0, 2 * np.pi, n_stars)
        det_xy = xy + error_px * np.stack([np.cos(turn), np.sin(turn)], 1)
    det_mag = mags[:n_stars] + ZERO_POINT + rng.normal(0, 0.2, n_stars)
    return attitude, StarTable.of(vectors, mags), det_xy.astype(np.float32), det_mag.astype(np.float32)


def _reference(xy, mag, ids, attitude, scale, vectors, mags, log_odds, max_tol_px, false_density=0.0):
    """rival_stars.rivalled_names in float64 NumPy, every catalog star a candidate."""
    f = CAMERA.f_px * scale
    sky = _sky(xy.astype(np.float64), attitude, scale)
    d = np.arccos(np.clip(sky @ vectors.T, -1, 1)) * f  # (N, M) px
    named = ids >= 0
    d_own = d[np.arange(len(xy)), np.maximum(ids, 0)]
    sigma = max(np.median(d_own[named]) / math.sqrt(2 * math.log(2)), rival_stars.SIGMA_FLOOR_PX)
    diff = mag - mags[np.maximum(ids, 0)]
    zero = np.median(diff[named])
    sigma_m = max(1.4826 * np.median(np.abs(diff[named] - zero)), rival_stars.MAG_FLOOR)

    def cost(o):
        return np.minimum(0.5 * (o / sigma_m) ** 2, rival_stars.MAG_OUTLIER_NATS)

    evidence = (d**2 - d_own[:, None] ** 2) / (2 * sigma**2) + cost(mag[:, None] - mags[None] - zero) \
        - cost(diff - zero)[:, None]
    rival = (np.arange(len(mags))[None] != ids[:, None]) & (d <= max_tol_px)
    # no star at all: the named star's 2-D Gaussian and brightness densities against a false
    # detection's, uniform over the frame (false_density per px²) and FALSE_MAG_SPAN
    mag_nats = (math.log(rival_stars.FALSE_MAG_SPAN / (math.sqrt(2 * math.pi) * sigma_m)) - cost(diff - zero)
                if named.sum() >= rival_stars.MIN_MAG_NAMES else 0.0)
    dof = max(2.0 * named.sum() - 4.0, 1.0)  # a bivariate t: σ̂ is the names' own
    own = (-0.5 * (dof + 2) * np.log1p(d_own**2 / (dof * sigma**2)) - math.log(2 * math.pi * sigma**2)
           + mag_nats)
    false_star = (own - math.log(false_density) < log_odds) if false_density > 0 else np.zeros(len(xy), bool)
    return named & (np.any(rival & (evidence < log_odds), axis=1) | false_star)


def _kernel(xy, mag, ids, attitude, scale, table, log_odds, max_tol_px, false_density=0.0):
    index = build_sky_index(table.unit_vectors, math.atan(max_tol_px * 1.1 / CAMERA.f_px))
    return np.asarray(rival_stars.rivalled_names(
        jnp.asarray(xy), jnp.ones(len(xy), bool), jnp.asarray(mag), jnp.asarray(ids, jnp.int32),
        jnp.asarray(attitude, jnp.float32), jnp.float32(scale), jnp.float32(0.0),
        jnp.asarray(table.unit_vectors), jnp.asarray(table.mag), index.device_arrays()[0],
        CAMERA.pinhole_numbers(), grid=index.grid, log_odds=jnp.float32(log_odds),
        max_tol_px=jnp.float32(max_tol_px), false_density=jnp.float32(false_density)))


FRAME_PX2 = CAMERA.width * CAMERA.height


@pytest.mark.parametrize("false_per_frame", [0.0, 1e3])
@pytest.mark.parametrize("seed", range(4))
def test_rivalled_names_match_a_numpy_reference(seed, false_per_frame):
    """Random frames full of close pairs, some names swapped to the neighbour: the kernel takes back
    exactly the names the float64 reference does (and some of each kind occur), also where a
    dense prior of false detections (one per 1,049 px²) makes the no-star rival take back more."""
    rng = np.random.default_rng(seed)
    scale = 1.0 + 0.01 * seed
    attitude, table, xy, mag = _frame(rng, scale=scale)
    ids = np.arange(len(xy))
    swap = rng.random(15) < 0.5
    ids[:15] = np.where(swap, 40 + np.arange(15), ids[:15])  # named after the neighbour
    vectors, mags = table.unit_vectors.astype(np.float64), table.mag.astype(np.float64)
    density = false_per_frame / FRAME_PX2
    want = _reference(xy, mag, ids, attitude, scale, vectors, mags, math.log(20.0), 10.0, density)
    got = _kernel(xy, mag, ids, attitude, scale, table, math.log(20.0), 10.0, density)
    np.testing.assert_array_equal(got, want)
    assert want.any() and not want.all()
    if false_per_frame:
        fewer = _reference(xy, mag, ids, attitude, scale, vectors, mags, math.log(20.0), 10.0)
        assert np.all(want >= fewer)  # the no-star rival only adds (its own test shows it can)


def test_a_false_detection_named_after_an_undetected_star_is_taken_back():
    """A false detection 4 px from a catalog star that was not detected, 1 mag brighter than it,
    named after it (no other catalog star near: the neighbour test cannot see it): taken back where
    one false detection per frame is expected, kept where none is asked about; the frame's right
    names (σ̂ = 1.5 px, 0.2 mag) all stand."""
    rng = np.random.default_rng(3)
    attitude, table, xy, mag = _frame(rng, n_stars=20, n_pairs=0)
    hidden = np.array([CAMERA.cx + 100.0, CAMERA.cy - 60.0])  # the undetected star
    vectors = np.vstack([table.unit_vectors, _sky(hidden[None], attitude)])
    mags = np.append(table.mag, 5.5)
    stars = StarTable.of(vectors, mags)
    xy = np.vstack([xy, hidden + np.array([4.0, 0.0])]).astype(np.float32)
    mag = np.append(mag, 5.5 + ZERO_POINT - 1.0).astype(np.float32)
    ids = np.arange(21)
    taken = _kernel(xy, mag, ids, attitude, 1.0, stars, math.log(20.0), 10.0, 1.0 / FRAME_PX2)
    np.testing.assert_array_equal(taken, np.arange(21) == 20)
    assert not _kernel(xy, mag, ids, attitude, 1.0, stars, math.log(20.0), 10.0).any()


def _close_pair():
    """A frame of 12 stars at σ̂ = 3 px (every other detection 3 √(2 ln 2) px off: the median
    residual) where detection 0 is the light of star 0 (V 4.3) landed 0.6 px from star 12 (V 5.6),
    8 px from its own star (RpNet's close pair on ``sgm2022`` at 3 px)."""
    rng = np.random.default_rng(7)
    attitude, table, xy, mag = _frame(rng, n_stars=12, n_pairs=0, error_px=3.0 * math.sqrt(2 * math.log(2)))
    own = np.array([CAMERA.cx, CAMERA.cy])  # star 0 moved to the centre, its detection 8 px off
    xy[0] = own + np.array([8.0, 0.0])
    neighbour = xy[0] + np.array([0.0, 0.6])
    vectors = np.vstack([_sky(own[None], attitude), table.unit_vectors[1:], _sky(neighbour[None], attitude)])
    mags = np.concatenate([[4.3], table.mag[1:], [5.6]])
    mag[0] = 4.3 + ZERO_POINT
    return attitude, StarTable.of(vectors, mags), xy, mag


def test_a_close_pair_named_after_the_wrong_star_is_taken_back():
    """The brighter star's detection named after its fainter neighbour (0.6 px away, 1.3 mag fainter
    than the detection) is taken back; named after its own star (8 px, 2.7 σ̂) it stands; with the
    neighbour as bright as the detection, the neighbour's name stands (position and brightness agree)."""
    attitude, table, xy, mag = _close_pair()
    ids = np.arange(12)
    wrong = ids.copy()
    wrong[0] = 12
    args = (attitude, 1.0)
    assert _kernel(xy, mag, wrong, *args, table, math.log(20.0), 10.0)[0]
    assert not _kernel(xy, mag, ids, *args, table, math.log(20.0), 10.0).any()
    brighter = StarTable.of(table.unit_vectors, np.append(table.mag[:12], 4.3))
    assert not _kernel(xy, mag, wrong, *args, brighter, math.log(20.0), 10.0).any()


def _identification(ids, attitude):
    return js.Identification(ids=jnp.asarray(ids, jnp.int32)[None], ok=jnp.ones(1, bool),
                             attitude=jnp.asarray(attitude, jnp.float32)[None],
                             focal_scale=jnp.ones(1), distortion_k1=jnp.zeros(1))


def _scene(xy, mag):
    n = len(xy)
    return js.Scene(xy=jnp.asarray(xy)[None], mag=jnp.asarray(mag)[None], valid=jnp.ones((1, n), bool),
                    truth=jnp.full((1, n), -1, jnp.int32), attitude=jnp.eye(3)[None],
                    overflow=jnp.zeros(1, bool))


def test_the_finishing_stage_takes_the_wrong_name_back_and_off_keeps_it():
    """Through ``finish`` (check only): the default ``rival_odds`` takes back the close pair's wrong
    name and keeps the other eleven; ``rival_odds=0`` keeps it; a scene left with fewer than three
    names is no longer claimed."""
    attitude, table, xy, mag = _close_pair()
    ids = np.arange(12)
    ids[0] = 12
    scenes = _scene(xy, mag)
    stage = Finishing(focal_search=(), hypotheses=0, max_false_match=1.0)
    kwargs = dict(rerun=None, camera=CAMERA, star_vectors=table.unit_vectors, star_mags=table.mag)
    got = finish(_identification(ids, attitude), scenes, stage, **kwargs).result
    want = np.where(np.arange(12) == 0, -1, ids)
    np.testing.assert_array_equal(np.asarray(got.ids)[0], want)
    assert bool(got.ok[0])
    kept = finish(_identification(ids, attitude), scenes, dataclasses.replace(stage, rival_odds=0.0),
                  **kwargs).result
    assert int(np.asarray(kept.ids)[0, 0]) == 12

    # three names: no zero point, so position alone judges, and the detection 0.6 px from star 12
    # loses its own (right) name to it; two names left cannot hold the claim
    three = np.where(np.arange(12) < 3, np.arange(12), -1)
    lost = rival_stars.without_rivalled_names(_identification(three, attitude), scenes, stars=table,
                                              camera=CAMERA, odds=20.0, max_tol_px=10.0, max_scale_error=0.1)
    assert not bool(lost.ok[0]) and np.all(np.asarray(lost.ids) == -1)
    assert np.all(np.isnan(np.asarray(lost.attitude)))


@pytest.mark.parametrize("value", [0.5, float("nan"), float("inf"), -1.0])
def test_finishing_rejects_bad_rival_odds(value):
    with pytest.raises(ValueError, match="rival_odds"):
        Finishing(rival_odds=value)


def test_the_papers_weigh_no_rivals():
    assert Finishing.off().rival_odds == 0 and Finishing().rival_odds == 20.0
    assert Finishing().false_per_frame == 1.0


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf")])
def test_finishing_rejects_a_bad_false_detection_prior(value):
    with pytest.raises(ValueError, match="false_per_frame"):
        Finishing(false_per_frame=value)
