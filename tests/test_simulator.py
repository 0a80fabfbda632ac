import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jstarid as js
from jstarid import random_streams as streams
from jstarid import simulator as sim_module


def _reference_visible(catalog, camera, attitude):
    """NumPy/SciPy: simulation rows in the frame and brighter than the limit, with their pixels."""
    c = np.asarray(attitude, np.float64)
    # The simulator's attitude is a proper rotation (SciPy's nearest rotation equals it); project
    # with the matrix itself so the reference does not inherit SciPy's re-orthonormalisation.
    np.testing.assert_allclose(Rotation.from_matrix(c).as_matrix(), c, atol=1e-6)
    v = catalog.sim_unit_vectors @ c.T
    front = v[:, 2] > 0
    vz = np.where(front, v[:, 2], 1.0)
    x = camera.cx + camera.f_px * v[:, 0] / vz
    y = camera.cy + camera.f_px * v[:, 1] / vz
    inside = front & (x >= 0) & (x <= camera.width - 1) & (y >= 0) & (y <= camera.height - 1)
    bright = catalog.sim_mag <= camera.mag_limit
    edge = front & (np.minimum.reduce([x, y, camera.width - 1 - x, camera.height - 1 - y]) < 0.01)
    return inside & bright, edge, np.stack([x, y], -1)


@pytest.mark.parametrize("preset", js.preset_names())
def test_noise_free_scenes_match_scipy_projection(catalog6, preset):
    cam = js.camera_preset(preset)
    scenes = js.simulate(jax.random.key(11), catalog6, cam, batch_size=200, capacity=256)
    assert not bool(scenes.overflow.any())
    sim_of_row = np.full(len(catalog6), -1)
    sim_of_row[catalog6.sim_row[catalog6.sim_row >= 0]] = np.nonzero(catalog6.sim_row >= 0)[0]
    n_checked = 0
    for b in range(scenes.batch_size):
        vis, edge, xy_ref = _reference_visible(catalog6, cam, scenes.attitude[b])
        valid = np.asarray(scenes.valid[b])
        truth = np.asarray(scenes.truth[b])[valid]
        xy = np.asarray(scenes.xy[b])[valid]
        # noise-free: no false stars; truth −1 only for stars beyond the catalog (a camera deeper
        # than the catalog, e.g. tetra3_test at V 7 with a V 6 catalog)
        in_cat = catalog6.sim_row >= 0
        got = set(sim_of_row[truth[truth >= 0]].tolist())
        want = set(np.nonzero(vis & in_cat)[0].tolist())
        ambiguous = set(np.nonzero(edge)[0].tolist())
        assert got - ambiguous == want - ambiguous, f"scene {b}"
        n_extra = int(np.sum(truth < 0))
        lo, hi = np.sum(vis & ~in_cat & ~edge), np.sum(vis & ~in_cat) + np.sum(edge & ~in_cat)
        assert lo <= n_extra <= hi
        np.testing.assert_allclose(xy[truth >= 0], xy_ref[sim_of_row[truth[truth >= 0]]],
                                   atol=1e-3)
        mags = np.asarray(scenes.mag[b])[valid]
        assert np.all(np.diff(mags) >= 0)  # brightest first
        n_checked += len(truth)
    assert n_checked > 200 * 3


def test_mode_b_centres_the_main_star(catalog6, sgm_camera):
    rows = np.arange(0, 5000, 50)
    scenes = js.simulate(jax.random.key(2), catalog6, sgm_camera, boresight_ids=rows, capacity=128)
    truth = np.asarray(scenes.truth)
    for i, r in enumerate(rows):
        hit = np.nonzero(truth[i] == r)[0]
        assert len(hit) == 1
        np.testing.assert_allclose(np.asarray(scenes.xy[i, hit[0]]), [sgm_camera.cx, sgm_camera.cy],
                                   atol=2e-3)
    # roll is random: the second-brightest star's direction angle is spread over the circle
    np.testing.assert_allclose(np.asarray(scenes.attitude[:, 2]),
                               catalog6.unit_vectors[rows], atol=1e-5)


def _pair(catalog, camera, noise, seed=5, batch=400, capacity=256):
    key = jax.random.key(seed)
    clean = js.simulate(key, catalog, camera, batch_size=batch, capacity=capacity)
    noisy = js.simulate(key, catalog, camera, noise, batch_size=batch, capacity=capacity)
    return clean, noisy


def test_position_noise_sigma(catalog6, sgm_camera):
    clean, noisy = _pair(catalog6, sgm_camera, js.NoiseConfig(position_sigma_px=2.0))
    np.testing.assert_array_equal(np.asarray(clean.truth), np.asarray(noisy.truth))
    d = np.asarray(noisy.xy - clean.xy)[np.asarray(clean.valid)]
    assert d.std(0) == pytest.approx([2.0, 2.0], rel=0.03)
    assert np.abs(d.mean(0)).max() < 0.05
    assert abs(np.corrcoef(d.T)[0, 1]) < 0.03


def test_noise_levels_as_a_batch_axis(catalog6, sgm_camera):
    levels = [0.0, 0.5, 1.0, 3.0]
    noise = js.noise_grid(300, position_sigma_px=levels)
    assert np.shape(noise.position_sigma_px) == (1200,)
    key = jax.random.key(8)
    clean = js.simulate(key, catalog6, sgm_camera, batch_size=1200, capacity=256)
    noisy = js.simulate(key, catalog6, sgm_camera, noise, batch_size=1200, capacity=256)
    for i, s in enumerate(levels):
        sl = slice(300 * i, 300 * (i + 1))
        d = np.asarray(noisy.xy[sl] - clean.xy[sl])[np.asarray(clean.valid[sl])]
        assert d.std() == pytest.approx(s, rel=0.05, abs=1e-6)


def test_missing_and_false_counts_exact(catalog6, sgm_camera):
    noise = js.NoiseConfig(n_missing=3, n_false=4)
    clean, noisy = _pair(catalog6, sgm_camera, noise)
    n_true_clean = np.asarray(jnp.sum(clean.valid & (clean.truth >= 0), -1))
    n_true = np.asarray(jnp.sum(noisy.valid & (noisy.truth >= 0), -1))
    n_false = np.asarray(jnp.sum(noisy.valid & (noisy.truth < 0), -1))
    np.testing.assert_array_equal(n_true, n_true_clean - np.minimum(3, n_true_clean))
    np.testing.assert_array_equal(n_false, 4)
    # the remaining true stars are a subset of the clean ones, at the same positions
    for b in range(20):
        t_clean = set(np.asarray(clean.truth[b])[np.asarray(clean.valid[b])].tolist())
        t_noisy = np.asarray(noisy.truth[b])[np.asarray(noisy.valid[b] & (noisy.truth[b] >= 0))]
        assert set(t_noisy.tolist()) <= t_clean
    f = np.asarray(noisy.valid & (noisy.truth < 0))
    fmag = np.asarray(noisy.mag)[f]
    assert fmag.min() >= 3.5 and fmag.max() <= 5.5
    fxy = np.asarray(noisy.xy)[f]
    assert fxy.min() >= 0 and fxy[:, 0].max() <= 1023 and fxy[:, 1].max() <= 1023


def test_false_ratio_and_radius(catalog6):
    cam = js.camera_preset("rpnet2019")
    radius = 300.0
    noise = js.NoiseConfig(false_ratio=0.25, false_radius_px=radius)
    scenes = js.simulate(jax.random.key(4), catalog6, cam, noise, batch_size=300, capacity=128)
    valid, truth = np.asarray(scenes.valid), np.asarray(scenes.truth)
    n_t = (valid & (truth >= 0)).sum(1)
    n_f = (valid & (truth < 0)).sum(1)
    ok = ~np.asarray(scenes.overflow)
    np.testing.assert_array_equal(n_f[ok], np.round(0.25 * n_t[ok] / 0.75).astype(int))
    fxy = np.asarray(scenes.xy)[valid & (truth < 0)]
    r = np.hypot(fxy[:, 0] - cam.cx, fxy[:, 1] - cam.cy)
    assert r.max() <= radius + 1e-3
    # uniform over the disk: half of the points within radius/√2
    assert np.mean(r < radius / np.sqrt(2)) == pytest.approx(0.5, abs=0.06)


def test_clutter_counts_and_magnitudes_follow_their_distributions(catalog6, sgm_camera):
    """One (B,) batch: a uniform count, a Poisson count, a false-to-true ratio with star-like
    magnitudes; each group against SciPy's distribution (counts) or the analytic CDF (magnitudes)."""
    from scipy import stats

    n = 1500
    group = np.repeat(np.arange(3), n)
    noise = js.NoiseConfig(
        n_false=np.where(group == 0, 2, 0).astype(np.int32),
        n_false_max=np.where(group == 0, 6, 0).astype(np.int32),
        false_mean=np.where(group == 1, 5.0, 0.0).astype(np.float32),
        false_per_true=np.where(group == 2, 2.0, 0.0).astype(np.float32),
        false_mag_min=3.0, false_mag_max=8.0,
        false_mag_slope=np.where(group == 2, js.CATALOG_MAG_SLOPE, 0.0).astype(np.float32))
    scenes = js.simulate(jax.random.key(21), catalog6, sgm_camera, noise, batch_size=3 * n, capacity=512)
    ok = ~np.asarray(scenes.overflow)
    valid, truth = np.asarray(scenes.valid), np.asarray(scenes.truth)
    n_t, n_f = (valid & (truth >= 0)).sum(1), (valid & (truth < 0)).sum(1)
    assert ok.all()
    # uniform on {2, …, 6}
    counts = np.bincount(n_f[group == 0], minlength=8)
    assert counts[:2].sum() == 0 and counts[7:].sum() == 0
    assert stats.chisquare(counts[2:7]).pvalue > 1e-3
    # Poisson of mean 5 (bins 0 … 11, the tail pooled)
    k = np.minimum(n_f[group == 1], 12)
    observed = np.bincount(k, minlength=13)
    expected = np.append(stats.poisson.pmf(np.arange(12), 5.0), stats.poisson.sf(11, 5.0)) * n
    assert stats.chisquare(observed, expected).pvalue > 1e-3
    # two false stars per true star, exactly
    np.testing.assert_array_equal(n_f[group == 2], 2 * n_t[group == 2])
    # magnitudes: uniform where the slope is 0, density ∝ 10^(0.47 m) where it is the catalog's
    fmag = np.asarray(scenes.mag)
    flat = fmag[(valid & (truth < 0)) & (group[:, None] < 2)]
    assert stats.kstest(flat, stats.uniform(3.0, 5.0).cdf).pvalue > 1e-3
    a = js.CATALOG_MAG_SLOPE * np.log(10.0)
    tilted = fmag[(valid & (truth < 0)) & (group[:, None] == 2)]
    assert stats.kstest(tilted, lambda m: np.expm1(a * (m - 3.0)) / np.expm1(a * 5.0)).pvalue > 1e-3
    assert np.median(tilted) > 6.5  # mostly faint, as stars are


@pytest.mark.parametrize("knee, slope, faint", [(6.0, 0.3, 2.0), (4.0, -0.5, 0.0), (9.0, 1.0, 3.0)])
def test_clutter_with_a_knee_follows_its_density(catalog6, sgm_camera, knee, slope, faint):
    """Two slopes meeting at a knee (a knee past the faint end: the one-slope draws, unchanged):
    against the CDF integrated numerically from the density."""
    from scipy import stats

    one = js.NoiseConfig(false_mean=20.0, false_mag_min=3.0, false_mag_max=8.0, false_mag_slope=slope)
    noise = dataclasses.replace(one, false_mag_knee=knee, false_mag_slope_faint=faint)
    scenes = js.simulate(jax.random.key(4), catalog6, sgm_camera, noise, batch_size=300, capacity=256)
    false = np.asarray(scenes.valid) & (np.asarray(scenes.truth) < 0)
    mags = np.asarray(scenes.mag)[false]
    grid = np.linspace(3.0, 8.0, 20001)
    density = np.where(grid < knee, 10.0 ** (slope * (grid - knee)), 10.0 ** (faint * (grid - knee)))
    cdf = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * np.diff(grid))])
    cdf /= cdf[-1]
    assert stats.kstest(mags, lambda m: np.interp(m, grid, cdf)).pvalue > 1e-3
    if knee >= 8.0:
        plain = js.simulate(jax.random.key(4), catalog6, sgm_camera, one, batch_size=300, capacity=256)
        np.testing.assert_array_equal(np.asarray(plain.mag), np.asarray(scenes.mag))


def test_catalog_mag_slope_is_the_catalogs(catalog6):
    """The constant is the slope of log10 N(≤ V) over V 4–8 of the full Hipparcos catalog."""
    stars = js.catalog.load_every_star(2000.0)
    counts = [np.sum(np.asarray(stars.mag) <= v) for v in (4.0, 8.0)]
    assert np.log10(counts[1] / counts[0]) / 4.0 == pytest.approx(js.CATALOG_MAG_SLOPE, abs=0.01)


def test_poisson_count_past_the_buffer_is_not_clipped():
    """A Poisson draw beyond the buffer comes back larger than it (the simulator flags overflow)."""
    one = jax.tree.map(lambda a: a[0], js.NoiseConfig(false_mean=4.0).broadcast(1))
    seeds = jax.vmap(streams.scene_seed)(jax.random.split(jax.random.key(0), 400))
    counts = jax.vmap(lambda s: sim_module._false_count(s, one, jnp.int32(10), 3))(seeds)
    assert int(counts.max()) == 4 and np.mean(np.asarray(counts) == 4) > 0.4  # P(N > 3) = 0.57


def test_magnitude_noise_lets_stars_appear_and_vanish(catalog6, sgm_camera):
    clean, noisy = _pair(catalog6, sgm_camera, js.NoiseConfig(magnitude_sigma=0.3), batch=500)
    valid = np.asarray(noisy.valid)
    truth = np.asarray(noisy.truth)
    assert np.sum(valid & (truth < 0)) > 50  # dimmer-than-limit stars appeared (not in catalog)
    vanished = 0
    for b in range(500):
        c = set(np.asarray(clean.truth[b])[np.asarray(clean.valid[b])].tolist())
        n = set(truth[b][valid[b]].tolist())
        vanished += len(c - n)
    assert vanished > 50
    # observed − catalog magnitude of bright stars (unaffected by the cut) has σ ≈ 0.3
    use = valid & (truth >= 0)
    dm = np.asarray(noisy.mag)[use] - catalog6.mag[truth[use]]
    bright = catalog6.mag[truth[use]] < 4.5
    assert dm[bright].std() == pytest.approx(0.3, rel=0.06)


def test_deterministic_and_jit_agrees(catalog6, sgm_camera):
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=0.2, n_missing=1, n_false=2)
    a = js.simulate(jax.random.key(9), catalog6, sgm_camera, noise, batch_size=3)
    b = js.simulate(jax.random.key(9), catalog6, sgm_camera, noise, batch_size=3)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with jax.disable_jit():
        c = js.simulate(jax.random.key(9), catalog6, sgm_camera, noise, batch_size=3)
    np.testing.assert_array_equal(np.asarray(a.truth), np.asarray(c.truth))
    np.testing.assert_array_equal(np.asarray(a.valid), np.asarray(c.valid))
    np.testing.assert_allclose(np.asarray(a.xy), np.asarray(c.xy), atol=1e-3)
    other = js.simulate(jax.random.key(10), catalog6, sgm_camera, noise, batch_size=3)
    assert not np.array_equal(np.asarray(a.xy), np.asarray(other.xy))


def test_small_batches_share_one_program_and_a_scene_is_its_keys(catalog6, sgm_camera):
    """Unsharded batches below the chunked size are drawn at a padded size (a power of two ≥ 16):
    batches of 1, 5 and 16 scenes compile stage 2 once, and a scene is the same in any of them (its
    key is the batch key's split, which holds its prefix at every length)."""
    noise = js.NoiseConfig(position_sigma_px=0.7, magnitude_sigma=0.1, n_false=1)
    key = jax.random.key(21)
    capacity = 37  # a width no other test of this process draws at
    programs = sim_module._scenes_batch._cache_size()
    full = js.simulate(key, catalog6, sgm_camera, noise, batch_size=16, capacity=capacity)
    for n in (1, 5):
        part = js.simulate(key, catalog6, sgm_camera, noise, batch_size=n, capacity=capacity)
        assert part.xy.shape == (n, capacity, 2)
        for x, y in zip(jax.tree.leaves(part), jax.tree.leaves(full[:n]), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert sim_module._scenes_batch._cache_size() - programs == 1
    # mode b with per-scene noise (padded with the last scene's values): each scene is the one its
    # own setting draws, alone or beside scenes of other settings
    rows = np.array([5, 9, 2])
    sigmas = np.array([0.0, 0.5, 1.0])
    mixed = js.simulate(key, catalog6, sgm_camera, js.NoiseConfig(position_sigma_px=sigmas),
                        boresight_ids=rows, capacity=capacity)
    alone = [js.simulate(key, catalog6, sgm_camera, js.NoiseConfig(position_sigma_px=sigma),
                         boresight_ids=rows, capacity=capacity) for sigma in sigmas]
    for i in range(3):
        for x, y in zip(jax.tree.leaves(mixed[i]), jax.tree.leaves(alone[i][i]), strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert not np.array_equal(np.asarray(mixed.xy[2]), np.asarray(alone[0].xy[2]))  # its σ applied


@pytest.mark.parametrize("narrow", [False, True])
def test_batch_equals_per_scene(catalog6, sgm_camera, narrow):
    # narrow: a large batch (chunked) of a 4° field, whose chunks mostly select with k = 16 of 64
    camera = js.Camera(512, 512, 7000.0, mag_limit=6.0) if narrow else sgm_camera
    n_batch = sim_module._CHUNK_MIN_BATCH if narrow else 6
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=0.2, n_missing=1, n_false=2)
    key = jax.random.key(12)
    batch = js.simulate(key, catalog6, camera, noise, batch_size=n_batch)
    check = list(range(6))
    if narrow:
        n_stars = np.asarray(batch.n_stars)
        assert np.median(n_stars) <= 8
        check.append(int(np.argmax(n_stars)))
    # Rebuild the per-scene inputs exactly as `simulate` does (its own plan: the sky index it
    # chose for this camera and noise) and call the per-scene function.
    index = sim_module._plan(catalog6, camera, noise, batch_size=n_batch, capacity=64, mode_b=False).index
    tables = sim_module._device_tables(catalog6)
    keys = jax.random.split(key, n_batch)
    per = noise.broadcast(n_batch)
    one_scene = jax.jit(functools.partial(
        sim_module._simulate_one, cells=jnp.asarray(index.cells), star_vec=tables[0],
        star_mag=tables[1], star_row=tables[2], cat_vec=tables[3], camera=camera, capacity=64,
        grid=index.grid, false_capacity=2, max_missing=1, mode_b=False))
    for i in check:
        one = one_scene(keys[i], jax.tree.map(lambda a, i=i: a[i], per), jnp.int32(0))
        np.testing.assert_array_equal(np.asarray(one.truth), np.asarray(batch.truth[i]))
        # the two compile the projection differently; float32 rounding of a direction (a few ulp,
        # ≈ 4 · 1.2e-7 rad) is 3.3e-3 px at the narrow camera's f = 7,000 px
        atol = max(1e-3, 4 * float(np.finfo(np.float32).eps) * camera.f_px)
        np.testing.assert_allclose(np.asarray(one.xy), np.asarray(batch.xy[i]), atol=atol)


def test_keep_brightest_same_for_every_selection_size():
    """Step 7 may select with any k ≥ the detections (the batch picks the smallest of
    ``_keep_sizes``): same scene as k = capacity and as NumPy's stable sort, ties by candidate order."""
    rng = np.random.default_rng(3)
    n, capacity = 100, 64
    assert sim_module._keep_sizes(64) == (16, 32, 64)
    assert sim_module._keep_sizes(200) == (16, 32, 64, 128, 200)
    assert sim_module._keep_sizes(10) == (10,)

    @functools.partial(jax.jit, static_argnames="k")  # a program per k, not one per operation
    def keep(seed, det, k):
        brightest = sim_module._brightest(det, k)
        return sim_module._keep_brightest(seed, js.NoiseConfig(), jnp.eye(3), det, brightest,
                                          capacity=capacity, n_cand=n)

    for trial in range(20):
        detected = np.zeros(n, bool)
        detected[rng.choice(n, size=rng.integers(0, 17), replace=False)] = True
        mag = np.round(rng.uniform(0.0, 3.0, n) * 2) / 2  # many exact ties
        det = sim_module._Detections(
            xy=jnp.asarray(rng.uniform(0, 1000, (n, 2)), jnp.float32), mag=jnp.asarray(mag, jnp.float32),
            detected=jnp.asarray(detected), truth=jnp.arange(n, dtype=jnp.int32),
            n_detected=jnp.int32(detected.sum()), false_overflow=jnp.bool_(False),
            sigma_px=jnp.ones((n,), jnp.float32))
        seed = jnp.asarray([trial, 7], jnp.uint32)
        scenes = [keep(seed, det, k) for k in (16, 32, 64)]
        expect = np.argsort(np.where(detected, mag, np.inf), kind="stable")[:detected.sum()]
        for scene in scenes:
            np.testing.assert_array_equal(np.asarray(scene.truth[:len(expect)]), expect)
            assert not np.asarray(scene.valid[len(expect):]).any()
            for field in ("xy", "mag", "truth", "valid", "overflow"):
                np.testing.assert_array_equal(np.asarray(getattr(scene, field)),
                                              np.asarray(getattr(scenes[-1], field)))


def test_overflow_flag_and_brightest_kept(catalog6, sgm_camera):
    big = js.simulate(jax.random.key(1), catalog6, sgm_camera, batch_size=50, capacity=256)
    small = js.simulate(jax.random.key(1), catalog6, sgm_camera, batch_size=50, capacity=8)
    n = np.asarray(big.n_stars)
    np.testing.assert_array_equal(np.asarray(small.overflow), n > 8)
    np.testing.assert_array_equal(np.asarray(small.truth), np.asarray(big.truth[:, :8]))


def test_empty_scenes_do_not_crash(catalog6):
    blind = js.Camera(1024, 1024, 2900.0, mag_limit=-3.0)
    scenes = js.simulate(jax.random.key(0), catalog6, blind, batch_size=8)
    assert not bool(scenes.valid.any())
    assert bool(jnp.all(scenes.truth == -1))


def test_bad_simulation_input(catalog6, sgm_camera):
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="capacity"):
        js.simulate(key, catalog6, sgm_camera, batch_size=4, capacity=0)
    with pytest.raises(ValueError, match="position_sigma_px"):
        js.simulate(key, catalog6, sgm_camera, js.NoiseConfig(position_sigma_px=-1), batch_size=4)
    with pytest.raises(ValueError, match="false_ratio"):
        js.simulate(key, catalog6, sgm_camera, js.NoiseConfig(false_ratio=1.0), batch_size=4)
    with pytest.raises(ValueError, match="n_missing"):
        js.simulate(key, catalog6, sgm_camera, js.NoiseConfig(n_missing=1.5), batch_size=4)
    with pytest.raises(ValueError, match="magnitude_sigma"):
        js.simulate(key, catalog6, sgm_camera, js.NoiseConfig(magnitude_sigma=np.nan), batch_size=4)
    with pytest.raises(ValueError, match="false_mag_min"):
        js.simulate(key, catalog6, sgm_camera, js.NoiseConfig(false_mag_min=6, false_mag_max=5),
                    batch_size=4)
    with pytest.raises(ValueError, match="batch_size"):
        js.simulate(key, catalog6, sgm_camera)
    with pytest.raises(ValueError, match="boresight_ids"):
        js.simulate(key, catalog6, sgm_camera, boresight_ids=np.array([0, len(catalog6)]))
    with pytest.raises(ValueError, match="shape"):
        js.simulate(key, catalog6, sgm_camera, js.NoiseConfig(position_sigma_px=np.ones(3)),
                    batch_size=4)
    with pytest.raises(ValueError, match="batch_size must be a positive integer"):
        js.simulate(key, catalog6, sgm_camera, batch_size=2.5)
    with pytest.raises(ValueError, match="capacity must be a positive integer"):
        js.simulate(key, catalog6, sgm_camera, batch_size=2, capacity=64.0)
    for not_a_key in (0, np.zeros(2, np.float32), jax.random.split(key, 2)):
        with pytest.raises(ValueError, match="key must be one PRNG key"):
            js.simulate(not_a_key, catalog6, sgm_camera, batch_size=2)
    legacy = js.simulate(jax.random.PRNGKey(0), catalog6, sgm_camera, batch_size=2)  # still taken
    assert legacy.batch_size == 2


def test_noise_config_is_a_pytree():
    noise = js.NoiseConfig(position_sigma_px=1.0)
    leaves = jax.tree.leaves(noise)
    assert len(leaves) == len(dataclasses.fields(noise))


@pytest.mark.production_numerics
def test_chunked_large_batch_equals_direct_path(catalog6, sgm_camera, monkeypatch):
    """Large batches take the sorted, chunked path; it must give exactly the direct path's scenes."""
    noise = js.NoiseConfig(position_sigma_px=1.0, magnitude_sigma=0.1, n_missing=1, n_false=2)
    key = jax.random.key(21)
    monkeypatch.setattr(sim_module, "_CHUNK_MIN_BATCH", 256)
    monkeypatch.setattr(sim_module, "_CHUNK", 64)
    monkeypatch.setattr(sim_module, "_WIDTH_STEP", 192)  # three list widths, not seven: each is compiled
    chunked = js.simulate(key, catalog6, sgm_camera, noise, batch_size=300)  # 4 chunks + a padded fifth
    monkeypatch.setattr(sim_module, "_CHUNK_MIN_BATCH", 10**9)
    direct = js.simulate(key, catalog6, sgm_camera, noise, batch_size=300)
    for a, b in zip(jax.tree.leaves(chunked), jax.tree.leaves(direct), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-4)


def test_scene_sampler_draws_what_simulate_draws_also_inside_jit(catalog6, sgm_camera):
    noise = js.NoiseConfig(position_sigma_px=np.linspace(0, 2, 12).astype(np.float32), n_false=1,
                           magnitude_sigma=0.1)
    key = jax.random.key(23)
    rows = np.arange(0, 1200, 100, dtype=np.int32)
    for mode_b, kwargs in ((True, dict(boresight_ids=rows)), (False, dict(batch_size=12))):
        want = js.simulate(key, catalog6, sgm_camera, noise, capacity=32, **kwargs)
        sampler = js.scene_sampler(catalog6, sgm_camera, noise, batch_size=12, capacity=32,
                                   mode_b=mode_b)
        eager = sampler(key, jnp.asarray(rows))
        traced = jax.jit(sampler.draw)(sampler.arrays, key, jnp.asarray(rows))
        for got in (eager, traced):
            for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-4)
    with pytest.raises(ValueError, match="batch_size"):
        js.scene_sampler(catalog6, sgm_camera, noise, batch_size=0)
    sampler = js.scene_sampler(catalog6, sgm_camera, noise, batch_size=12, mode_b=True)
    with pytest.raises(ValueError, match="rows"):  # a mode-b sampler needs its boresight rows
        sampler(key)
    with pytest.raises(ValueError, match="rows"):
        sampler(key, jnp.zeros((5,), jnp.int32))


def test_sharded_simulation_equals_single_device(catalog6, sgm_camera, several_devices):
    noise = js.noise_grid(5, position_sigma_px=[0.0, 1.0, 2.0], n_false=1)
    key = jax.random.key(31)
    one = js.simulate(key, catalog6, sgm_camera, noise, batch_size=15)
    many = js.simulate(key, catalog6, sgm_camera, noise, batch_size=15, shard=True)
    assert len(many.xy.sharding.device_set) == len(jax.devices())
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(many), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-4)


def test_repeated_sharded_calls_do_not_recompile(catalog6, sgm_camera):
    from jstarid.runtime import devices as sweep

    js.simulate(jax.random.key(1), catalog6, sgm_camera, batch_size=8, shard=True)
    before = sweep._compiled.cache_info().currsize
    js.simulate(jax.random.key(2), catalog6, sgm_camera, batch_size=8, shard=True)
    assert sweep._compiled.cache_info().currsize == before


def test_second_call_with_new_key_does_not_recompile(catalog6, sgm_camera):
    noise = js.NoiseConfig(position_sigma_px=0.5)
    js.simulate(jax.random.key(1), catalog6, sgm_camera, noise, batch_size=8)
    sizes = (sim_module._scenes_batch._cache_size(), sim_module._attitudes._cache_size())
    js.simulate(jax.random.key(2), catalog6, sgm_camera, js.NoiseConfig(position_sigma_px=0.9),
                batch_size=8)
    assert (sim_module._scenes_batch._cache_size(), sim_module._attitudes._cache_size()) == sizes


def test_given_attitudes_are_the_scenes_attitudes(catalog6, sgm_camera, several_devices):
    """Mode c: SciPy's random rotations as the attitudes; the noise-free stars are where they put them
    (the reference projection), sharded and not, and bad rotations are refused."""
    given = Rotation.random(12, random_state=5).as_matrix()
    scenes = js.simulate(jax.random.key(3), catalog6, sgm_camera, attitudes=given, capacity=128)
    many = js.simulate(jax.random.key(3), catalog6, sgm_camera, attitudes=given, capacity=128, shard=True)
    for a, b in zip(jax.tree.leaves(scenes), jax.tree.leaves(many), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-4)
    np.testing.assert_allclose(np.asarray(scenes.attitude), given, atol=1e-6)
    sim_of_row = np.full(len(catalog6), -1)
    sim_of_row[catalog6.sim_row[catalog6.sim_row >= 0]] = np.nonzero(catalog6.sim_row >= 0)[0]
    for b in range(12):
        vis, edge, xy_ref = _reference_visible(catalog6, sgm_camera, given[b])
        valid = np.asarray(scenes.valid[b])
        truth = np.asarray(scenes.truth[b])[valid]
        rows = sim_of_row[truth[truth >= 0]]
        ambiguous = set(np.nonzero(edge)[0].tolist())
        assert set(rows.tolist()) - ambiguous == set(np.nonzero(vis)[0].tolist()) - ambiguous
        np.testing.assert_allclose(np.asarray(scenes.xy[b])[valid][truth >= 0], xy_ref[rows], atol=1e-3)
    with pytest.raises(ValueError, match="finite rotation"):
        js.simulate(jax.random.key(3), catalog6, sgm_camera, attitudes=2 * given)
    with pytest.raises(ValueError, match="without boresight_ids"):
        js.simulate(jax.random.key(3), catalog6, sgm_camera, attitudes=given, boresight_ids=np.arange(12))
