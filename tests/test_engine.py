"""The sweep engine (:mod:`jstarid.engine`): levels, entries, equality with direct calls, chunking,
determinism, grids, save/load and bad arguments."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import jstarid as js
from jstarid.config_tree import with_fields
from jstarid.engine import levels as lv
from jstarid.metrics import CORRECT, WRONG, wilson_interval


def _mlv_entry(**changes):
    mlv = js.algorithms.get("mlv")
    return js.Entry("mlv", "mlv", mlv.Config(n_boresights=20_000, batch_chunk=100, **changes))


def _small_sweep(**kw):
    args = dict(algorithms=["oracle", _mlv_entry()], camera="mlv2021",
                axes={"position_sigma_px": [0.0, 2.0]}, fixed={"magnitude_sigma": 0.3}, scenes=12,
                seed=4, catalog=js.load_catalog(5.5), progress=False)
    return js.sweep(**{**args, **kw})


@pytest.fixture(scope="module")
def small():
    return _small_sweep()


def _small_scenes():
    """(catalog, camera, scenes): the scenes ``_small_sweep`` draws, drawn by hand."""
    key_scenes, _ = jax.random.split(jax.random.key(4))
    cat, cam = js.load_catalog(5.5), js.camera_preset("mlv2021")
    noise = js.noise_grid(12, position_sigma_px=[0.0, 2.0], magnitude_sigma=0.3)
    return cat, cam, js.simulate(key_scenes, cat, cam, noise, batch_size=24, capacity=64)


def test_level_grid_is_the_product_first_axis_slowest():
    grid = lv.level_grid({"position": [0, 1], "n_false": [0, 2, 4]})
    assert grid[:4] == [{"position_sigma_px": 0.0, "n_false": 0}, {"position_sigma_px": 0.0, "n_false": 2},
                        {"position_sigma_px": 0.0, "n_false": 4}, {"position_sigma_px": 1.0, "n_false": 0}]
    noise = lv.level_noise(grid, 3, {"magnitude_sigma": 0.2})
    assert np.asarray(noise.n_false).tolist() == [0] * 3 + [2] * 3 + [4] * 3 + [0] * 3 + [2] * 3 + [4] * 3
    assert noise.magnitude_sigma == 0.2


def test_clutter_axes_by_their_short_names():
    grid = lv.level_grid({"false-per-true": [0, 5, 10], "false-mean": [20]})
    assert grid[2] == {"false_per_true": 10.0, "false_mean": 20.0}
    noise = lv.level_noise(grid, 2, {"false_mag_slope": js.CATALOG_MAG_SLOPE})
    assert np.asarray(noise.false_per_true).tolist() == [0, 0, 5, 5, 10, 10]


@pytest.mark.parametrize("axes, match", [
    ({}, "one or two"), ({"a": [1], "b": [1], "c": [1]}, "one or two"),
    ({"wobble": [1]}, "unknown axis"), ({"position": []}, "no values"),
    ({"position": [0, 1], "position_sigma_px": [2]}, "repeat"),
])
def test_level_grid_rejects_bad_axes(axes, match):
    with pytest.raises(ValueError, match=match):
        lv.level_grid(axes)


def test_level_noise_rejects_bad_values():
    with pytest.raises(ValueError, match="position_sigma_px"):
        lv.level_noise(lv.level_grid({"position": [-1.0]}), 2)
    with pytest.raises(ValueError, match="both a noise axis and a fixed"):
        lv.level_noise(lv.level_grid({"position": [1.0]}), 2, {"position_sigma_px": 1.0})
    with pytest.raises(ValueError, match="bad noise setting"):
        lv.level_noise(lv.level_grid({"position": [1.0]}), 2, {"sparkle": 1.0})


@pytest.mark.parametrize("k, n", [(0, 200), (200, 200), (37, 50), (1, 3)])
def test_wilson_interval_matches_scipy(k, n):
    ref = stats.binomtest(k, n).proportion_ci(0.95, method="wilson")
    lo, hi = wilson_interval(k, n)
    np.testing.assert_allclose([lo, hi], [ref.low, ref.high], atol=2e-4)  # z = 1.96 vs 1.95996…


def test_sweep_equals_direct_identify_calls(small):
    """The engine's outcomes are those of simulate + identify + scene_outcomes called by hand."""
    cat, cam, scenes = _small_scenes()
    entry = _mlv_entry()
    mlv = js.algorithms.get("mlv")
    direct = mlv.identify(mlv.build_database(cat, cam, entry.config, progress=False), scenes,
                          entry.config)
    codes = np.asarray(js.scene_outcomes(scenes, direct, "strict")["outcome"])
    assert small.labels == ["oracle", "mlv"]
    np.testing.assert_array_equal(small.scenes["outcome"][:, 1], codes)
    np.testing.assert_array_equal(small.level_of, np.repeat([0, 1], 12))
    rows = small.rows()
    assert [(r["label"], r["position_sigma_px"]) for r in rows] == [
        ("oracle", 0.0), ("oracle", 2.0), ("mlv", 0.0), ("mlv", 2.0)]
    for row, part in zip(rows[2:], (slice(0, 12), slice(12, 24)), strict=True):
        rep = js.evaluate(scenes[part], direct[part], "strict")
        assert row["identification_rate"] == rep["identification_rate"]
        assert row["misid_rate"] == rep["misid_rate"] and row["failure_rate"] == rep["failure_rate"]
        assert row["identification_low"] <= row["identification_rate"] <= row["identification_high"]
    assert rows[0]["identification_rate"] == 1.0 and rows[0]["boresight_err_arcsec_median"] < 1.0


def test_every_claim_carries_its_false_match_probability(small):
    """The sweep records each claim's P: the one MLV's finishing stage decided by, and for the
    oracle (no stage) that of its names under their Wahba attitude; rows give the claims' median
    and whether P is calibrated (:func:`jstarid.false_match.calibrated`), the table both."""
    from jstarid.false_match import SMALLEST_P, false_match_probability, with_names_attitude

    cat, cam, scenes = _small_scenes()
    entry = _mlv_entry()
    mlv = js.algorithms.get("mlv")
    direct = mlv.identify(mlv.build_database(cat, cam, entry.config, progress=False), scenes, entry.config)
    ok = np.asarray(direct.ok)
    assert ok.all() and direct.false_match is not None
    np.testing.assert_allclose(small.scenes["false_match"][:, 1], np.asarray(direct.false_match), rtol=1e-3)
    assert np.all(small.scenes["false_match"][:, 1] <= entry.config.finishing.max_false_match)
    oracle = js.algorithms.get("oracle")
    truth = oracle.identify(oracle.build_database(cat, cam), scenes)
    assert truth.false_match is None
    located = with_names_attitude(truth, scenes, cat, cam)
    by_hand = np.maximum(false_match_probability(scenes, located, cat.unit_vectors, cam), SMALLEST_P)
    np.testing.assert_allclose(small.scenes["false_match"][:, 0], by_hand, rtol=1e-3)
    assert np.all(by_hand < 1e-9)  # a dozen true names: no coincidence (float32 keeps P ≥ 1.2e-38)
    rows = small.rows()
    first_level = np.asarray(direct.false_match)[:12]
    assert rows[2]["false_match_median"] == pytest.approx(float(np.median(first_level)))
    assert all(r["false_match_calibrated"] is True for r in rows)
    assert "claims' false-match P (median)" in small.table()
    # calibration speaks of attitudes: one claim 20 px off at P = 1e-12 among 12 is not calibrated
    off = {k: v.copy() for k, v in small.scenes.items()}
    off["boresight_err_arcsec"][0, 1] = 20 * cam.pixel_scale_arcsec
    off["false_match"][0, 1] = 1e-12
    assert dataclasses.replace(small, scenes=off).rows()[2]["false_match_calibrated"] is False
    off["boresight_err_arcsec"][0, 1] = 5 * cam.pixel_scale_arcsec  # a right attitude, a pixel or two off
    assert dataclasses.replace(small, scenes=off).rows()[2]["false_match_calibrated"] is True
    older = dataclasses.replace(small, scenes={k: v for k, v in small.scenes.items() if k != "false_match"})
    assert older.rows()[0]["false_match_median"] is None  # a sweep saved before P was recorded


def test_rows_of_the_scenes_with_so_many_true_stars(small, tmp_path):
    """``rows(stars=(lo, hi))`` scores only the scenes with lo … hi true stars among their detections,
    counted here from the scenes themselves."""
    _, _, scenes = _small_scenes()
    n_true = (np.asarray(scenes.valid) & (np.asarray(scenes.truth) >= 0)).sum(1)
    np.testing.assert_array_equal(small.stars, n_true)
    lo, hi = np.percentile(n_true, [25, 75]).astype(int)
    chosen = (n_true >= lo) & (n_true <= hi)
    assert 0 < chosen.sum() < 24  # a range that leaves some scenes out
    rows = small.rows(stars=(lo, hi))
    for row, level in zip(rows[2:], (0, 1), strict=True):
        take = chosen & (small.level_of == level)
        codes = small.scenes["outcome"][take, 1]
        assert row["stars"] == f"{lo}–{hi}" and row["scenes"] == take.sum()
        assert row["n_correct"] == np.sum(codes == CORRECT) and row["n_wrong"] == np.sum(codes == WRONG)
        assert row["scenes_per_second"] == small.rows()[2 + level]["scenes_per_second"]
    assert f"| {lo}–{hi} |" in small.table(stars=(lo, hi))
    small.save(tmp_path)
    assert js.load_sweep(tmp_path).rows(stars=(lo, hi)) == rows
    with pytest.raises(ValueError, match="lo ≤ hi"):
        small.rows(stars=(3, 2))
    with pytest.raises(ValueError, match="no star counts"):
        dataclasses.replace(small, stars=None).rows(stars=(1, 2))


def test_chunking_and_seed(small):
    """Chunks bound memory without changing an outcome; the seed alone decides the scenes."""
    chunked = _small_sweep(chunk_size=5)
    assert chunked.equal_outcomes(small)
    other = _small_sweep(seed=5)
    assert not np.array_equal(other.scenes["n_identified"], small.scenes["n_identified"])


@pytest.mark.slow
def test_grid_runs_as_one_batch_and_equals_single_entries():
    mlv = js.algorithms.get("mlv")
    base = _mlv_entry().config
    grid = js.grid("mlv", base, th1=[0, 2], eps_deg=[0.1, 0.25])
    assert [e.label for e in grid] == ["mlv th1=0 eps_deg=0.1", "mlv th1=0 eps_deg=0.25",
                                       "mlv th1=2 eps_deg=0.1", "mlv th1=2 eps_deg=0.25"]
    kw = dict(camera="mlv2021", axes={"position": [2.5]}, fixed={"magnitude_sigma": 0.3}, scenes=16,
              catalog=js.load_catalog(5.5), progress=False)
    batched = js.sweep(grid, **kw)
    separate = js.sweep([e._replace(group="") for e in grid], **kw)
    # the same names, counts and flags; the camera check's floats (P) to rounding: an entry alone runs
    # its check in calls of other widths (SweepResult.equal_outcomes)
    assert batched.equal_outcomes(separate, rtol=1e-3)
    assert len({r["identification_rate"] for r in batched.rows()}) > 1  # the grid matters
    # Δv shapes MLV's lookup tables: not batchable, so each point runs with its own database
    dv = js.grid("mlv", base, dv1=[3e-5, 6e-5])
    dv_batched = js.sweep(dv, **kw)
    assert dv_batched.equal_outcomes(js.sweep([e._replace(group="") for e in dv], **kw))
    assert dv_batched.rows()[0]["dv1"] == 3e-5
    with pytest.raises(ValueError, match="differ only"):
        mlv.identify_grid(None, None, [base, dataclasses.replace(base, n_stars=8)])
    with pytest.raises(ValueError, match="no field"):
        js.grid("mlv", base, wobble=[1])


def test_equal_outcomes_holds_counts_exactly_and_measured_floats_within_rtol(small):
    """``equal_outcomes`` is bit equality by default; with ``rtol`` (a grid's entry run alone may round
    its camera check's floats otherwise) counts and flags stay exact and floats agree within it."""
    floats = [k for k, v in small.scenes.items() if np.asarray(v).dtype.kind == "f"]
    counts = [k for k, v in small.scenes.items() if np.asarray(v).dtype.kind in "iub"]
    assert floats and counts

    def changed(key, change):
        scenes = {k: np.array(v) for k, v in small.scenes.items()}
        scenes[key] = change(scenes[key])
        return dataclasses.replace(small, scenes=scenes)

    assert small.equal_outcomes(small)
    rounded = changed(floats[0], lambda a: a * (1 + 1e-5))
    assert rounded.equal_outcomes(small, rtol=1e-3) and not rounded.equal_outcomes(small)
    assert not changed(floats[0], lambda a: a * 1.01 + 1.0).equal_outcomes(small, rtol=1e-3)
    assert not changed(counts[0], lambda a: a + 1).equal_outcomes(small, rtol=1e-3)


def test_save_and_load_round_trip(small, tmp_path):
    small.save(tmp_path)
    back = js.load_sweep(tmp_path)
    assert back.equal_outcomes(small) and back.rows() == small.rows()
    # XLA's compile time is recorded per entry and level, a part of the wall time
    assert small.compile_seconds.shape == small.seconds.shape
    assert np.all((small.compile_seconds >= 0) & (small.compile_seconds <= small.seconds))
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["rows"][0]["label"] == "oracle"
    assert (tmp_path / "rates.png").stat().st_size > 10_000
    table = (tmp_path / "table.md").read_text()
    assert "| mlv | 2 | 12 |" in table and "Wilson" in table
    with pytest.raises(FileNotFoundError):
        js.load_sweep(tmp_path / "nothing")


@pytest.mark.parametrize("kw, match", [
    (dict(algorithms="nope"), "unknown algorithm"), (dict(camera="nope"), "unknown camera"),
    (dict(scenes=0), "scenes must be"), (dict(axes={"position": [-1.0]}), "position_sigma_px"),
    (dict(criterion="lenient"), "unknown criterion"), (dict(boresight="moon"), "boresight"),
])
def test_bad_arguments_are_clear_errors(kw, match):
    with pytest.raises(ValueError, match=match):
        _small_sweep(**kw)


def test_sgm_criterion_is_scored_on_the_entry_s_own_circle():
    """A result naming only the stars within 3° of the main star meets the sgm criterion on a 3°
    circle and not on the default 6° one."""
    from jstarid.engine.run import _score

    cam = js.camera_preset("sgm2022")
    cat = js.load_catalog(6.0)
    scenes = js.simulate(jax.random.key(0), cat, cam, js.NoiseConfig(), batch_size=8, capacity=128,
                         boresight_ids=np.arange(100, 108))
    near = np.asarray(js.metrics.in_neighbor_circle(scenes, cam, 3.0))
    named = near & np.asarray(scenes.valid)
    ids = np.where(named, np.asarray(scenes.truth), -1).astype(np.int32)
    result = js.Identification(ids=ids, ok=np.ones(8, bool))
    narrow = _score(scenes, result, cat, cam, "sgm", radius_deg=3.0)["outcome"]
    wide = _score(scenes, result, cat, cam, "sgm")["outcome"]
    assert np.all(narrow == js.metrics.CORRECT)
    assert np.all(wide == js.metrics.INCOMPLETE)  # stars between 3° and 6° left unnamed


def test_an_algorithm_that_cannot_work_on_the_camera_stops_everything_first(monkeypatch):
    """SGM on a 6° × 4.6° field: its published 6° circle, or (the circle that fits) a V ≤ 10
    database of 3.6 GiB: one clear error before any scene or database."""
    from jstarid.engine import run

    sgm = js.algorithms.get("sgm")
    monkeypatch.setattr(run, "simulate_levels", lambda *a, **k: pytest.fail("simulated anyway"))
    with pytest.raises(ValueError, match=r"sgm: SGM's database for camera narrow_twin would hold "
                                         r"106,172 neighbor graphs of up to 95 stars \(r = 2°"):
        js.sweep("mlv,sgm", "narrow_twin", scenes=2)
    published = js.engine.entries([js.Entry("sgm 6°", "sgm", sgm.Config())])
    with pytest.raises(ValueError, match=r"sgm 6°: SGM's neighbor circle r = 6° does not fit the 2\.28°"):
        js.sweep(published, "narrow_twin", scenes=2)
    small = js.engine.entries([js.Entry("sgm small", "sgm", sgm.Config(radius_deg=2.0))])
    js.engine.check_camera(small, js.camera_preset("narrow_twin"), js.load_catalog(6.0))  # fits


# --- sweeps from pixels (engine.pixels) ---------------------------------------------------------------

PIXEL_CAMERA = js.Camera(256, 256, 128.0 / np.tan(np.radians(10.0)), mag_limit=6.0, name="small20")


def test_label_detections_takes_the_nearest_star_within_reach():
    from jstarid.engine.pixels import label_detections

    rng = np.random.default_rng(0)
    stars = rng.uniform(0, 100, (3, 20, 2))
    star_valid = np.arange(20)[None, :] < np.array([[20], [12], [0]])
    truth = rng.integers(-1, 500, (3, 20))
    det = np.concatenate([stars[:, :8] + rng.normal(0, 0.5, (3, 8, 2)), rng.uniform(0, 100, (3, 4, 2))], 1)
    det_valid = np.ones((3, 12), bool)
    det_valid[1, 10:] = False
    got = np.asarray(label_detections(det, det_valid, stars, star_valid, truth))
    for b in range(3):
        for n in range(12):
            d = np.where(star_valid[b], np.linalg.norm(det[b, n] - stars[b], axis=1), np.inf)
            want = truth[b, np.argmin(d)] if det_valid[b, n] and d.min() <= 1.5 else -1
            assert got[b, n] == want


@pytest.fixture(scope="module")
def pixel_sweep():
    return js.sweep(["oracle"], PIXEL_CAMERA, axes={"exposure_s": [0.0003, 0.1]}, scenes=6, seed=2,
                    pixels=True, progress=False)


def test_sweep_from_pixels_follows_the_exposure(pixel_sweep):
    rows = pixel_sweep.rows()
    assert [r["exposure_s"] for r in rows] == [0.0003, 0.1]
    # at 0.1 s every star to the limit gives ≥ 500 e⁻: the oracle names what the pixels show
    assert rows[1]["identification_rate"] == 1.0
    # 1.5 e⁻ at the limit: too few stars are detected
    assert rows[0]["identification_rate"] < rows[1]["identification_rate"]
    s = pixel_sweep.settings
    assert s["pixels"] and [x["exposure_s"] for x in s["sensors"]] == [0.0003, 0.1]
    assert s["sky_overflow"] == 0


def test_sweep_from_pixels_equals_compare_on_its_scenes_and_repeats(pixel_sweep):
    drawn = js.engine.simulate_levels(PIXEL_CAMERA, axes={"exposure_s": [0.0003, 0.1]}, scenes=6,
                                      seed=2, pixels=True)
    scenes = jax.device_get(drawn.scenes)
    truth, valid = np.asarray(scenes.truth), np.asarray(scenes.valid)
    # bright frames: most detections are catalog stars, labelled; none labelled where not valid
    assert np.all(truth[~valid] == -1) and np.mean(truth[6:][valid[6:]] >= 0) > 0.7
    again = js.compare(drawn.scenes, ["oracle"], drawn.catalog, drawn.camera, level_of=drawn.level_of,
                       levels=drawn.levels, progress=False)
    for a, b in zip(again.rows(), pixel_sweep.rows(), strict=True):
        assert a["identification_rate"] == b["identification_rate"] and a["scenes"] == b["scenes"]
    twice = js.engine.simulate_levels(PIXEL_CAMERA, axes={"exposure_s": [0.0003, 0.1]}, scenes=6,
                                      seed=2, pixels=True)
    np.testing.assert_array_equal(np.asarray(twice.scenes.xy), np.asarray(scenes.xy))


def test_sweep_from_the_sensors_detection_model_follows_the_exposure():
    """``detection="sensor"``: each exposure's DetectionModel.from_sensor, no rendering — the same
    verdict as the pixels above, and a fixed model for every scene."""
    result = js.sweep(["oracle"], PIXEL_CAMERA, axes={"exposure_s": [0.0003, 0.1]}, scenes=6, seed=2,
                      detection="sensor", progress=False)
    rows = result.rows()
    assert [r["exposure_s"] for r in rows] == [0.0003, 0.1]
    assert rows[1]["identification_rate"] == 1.0
    assert rows[0]["identification_rate"] < rows[1]["identification_rate"]
    s = result.settings
    assert s["detection"] == "sensor"
    assert s["models"][0]["zero_point_e"] < s["models"][1]["zero_point_e"]
    drawn = js.engine.simulate_levels(PIXEL_CAMERA, axes={"position": [0.0]}, scenes=4, seed=1,
                                      detection=js.DetectionModel.from_sensor(PIXEL_CAMERA))
    assert drawn.settings["detection"]["threshold_e"] > 0 and int(drawn.scenes.n_stars.sum()) > 0
    with pytest.raises(ValueError, match="drop detection"):
        js.sweep(["oracle"], PIXEL_CAMERA, scenes=2, pixels=True, detection="sensor", progress=False)
    with pytest.raises(ValueError, match="'sensor'"):
        js.sweep(["oracle"], PIXEL_CAMERA, scenes=2, detection="pixels", progress=False)


def test_sensor_settings_need_a_sweep_from_pixels():
    with pytest.raises(ValueError, match="sensor axis needs a sweep from pixels"):
        js.sweep(["oracle"], PIXEL_CAMERA, axes={"exposure": [0.1]}, scenes=2, progress=False)
    with pytest.raises(ValueError, match="for sweeps from pixels"):
        js.sweep(["oracle"], PIXEL_CAMERA, scenes=2, sensor=js.SensorConfig(), progress=False)
    with pytest.raises(ValueError, match="exposure_s must be a positive"):
        js.sweep(["oracle"], PIXEL_CAMERA, axes={"exposure": [-1.0]}, scenes=2, pixels=True, progress=False)


def test_sweep_from_pixels_centres_boresight_stars():
    catalog = js.load_catalog(6.0)
    drawn = js.engine.simulate_levels(PIXEL_CAMERA, axes={"exposure_s": [0.1]}, scenes=3, seed=1,
                                      boresight="stars", catalog=catalog, pixels=True)
    rng_rows = np.asarray(jax.random.randint(jax.random.split(jax.random.key(1))[1], (3,), 0, len(catalog)))
    boresight = np.asarray(drawn.scenes.attitude)[:, 2, :]  # the camera's +z in ICRS
    np.testing.assert_allclose(boresight, catalog.unit_vectors[rng_rows], atol=1e-5)


def test_boresight_rows_found_in_a_catalog_that_differs():
    from jstarid.engine.run import _rows_in

    catalog = js.load_catalog(6.0)
    other = js.load_catalog(6.0, double_sep_deg=0.5)  # drops the fainter of many more pairs
    rows = np.arange(len(catalog))
    got = _rows_in(other, catalog, rows)
    same = np.isin(catalog.hip, other.hip)
    assert not same.all() and np.all(other.hip[got[same]] == catalog.hip[same])
    cos = np.sum(catalog.unit_vectors[~same] * other.unit_vectors[got[~same]], axis=1)
    assert np.all(np.degrees(np.arccos(np.clip(cos, -1, 1))) <= 0.5 + 1e-6)  # its kept neighbour


def test_frames_config_turns_on_sgm_subgraph_search_only():
    cam = js.camera_preset("tetra3_test")
    sgm_frames = js.engine.default_config("sgm", camera=cam, frames=True)
    sgm_sim = js.engine.default_config("sgm", camera=cam)
    assert sgm_frames.subgraph.on and not sgm_sim.subgraph.on
    assert with_fields(sgm_frames, {"subgraph": False}) == sgm_sim
    assert js.engine.default_config("mlv", camera=cam, frames=True) == js.engine.default_config(
        "mlv", camera=cam)


def test_a_grid_run_config_by_config_is_timed_config_by_config():
    """Successive ``identify`` calls of a grid (no ``identify_grid``) each get their own wall time,
    and their own XLA compile time (a program compiled in the first call counts there only)."""
    import time
    import types

    from jstarid.engine.run import _runner

    def identify(db, scenes, config):
        if config == 0.0:  # a program no call has compiled before
            jax.jit(lambda x: jnp.cos(x) * 7.0 - 2.0)(jnp.arange(3.0)).block_until_ready()
        time.sleep(config)
        return js.Identification(ids=np.zeros((1, 2), np.int32), ok=np.ones(1, bool), attitude=None)

    db = types.SimpleNamespace(cache_key=lambda: "k")
    results, shares, compiled = _runner(types.SimpleNamespace(identify=identify), [db, db], [0.0, 1.5])(None)
    # One tiny compile on a loaded 2-core runner took 0.107 s; the gap between the calls is wide.
    assert len(results) == 2 and shares[0] < 1.0 < 1.5 <= shares[1]
    assert 0 < compiled[0] <= shares[0] and compiled[1] == 0
