"""The algorithm contract (:mod:`jstarid.algorithms.base`), checked on every registered algorithm.

Each algorithm runs in a small "world" (catalog, camera, config) chosen so the suite stays fast; an
algorithm registered without an entry in ``WORLDS`` runs on the default world (V ≤ 6, the
``sgm2022`` camera, ``Config()``) and must pass there or fail loudly. The optional hooks
(:data:`jstarid.algorithms.base.HOOKS`) are checked on every registered algorithm, and their
defaults on a minimal algorithm that declares none of them (:func:`_hookless_module`).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import importlib.machinery
import re
import sys
import types
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jstarid as js
from jstarid.algorithms import base
from jstarid.config_tree import value_at

NAMES = js.algorithms.names()


def _rpnet_config():
    rpnet = js.algorithms.get("rpnet")
    training = rpnet.Training(dae_lr=3e-3, clf_lr=3e-3, dae_steps=200, clf_steps=200, batch_size=128,
                              eval_every=100, eval_size=128, pool_batches=3, sim_capacity=64, seed=1)
    return rpnet.Config(rho_deg=20.0, e_deg=0.1, gen_widths=(64, 128), clf_width=64,
                        training=training, pair_tol_px=5.0, match_tol_px=5.0, batch_chunk=16)


# name → (catalog V limit, camera, config factory); small but realistic settings per algorithm (the
# pyramid's contract tests are bound by its execution, which grows with the stars per frame: MLV's
# camera at V 5.5 holds fewer than the default world; test_pyramid.py runs it on sgm2022)
WORLDS = {
    "sgm": (6.0, lambda: js.camera_preset("sgm2022"),
            lambda: js.algorithms.get("sgm").Config()),
    "mlv": (5.5, lambda: js.camera_preset("mlv2021"),
            lambda: js.algorithms.get("mlv").Config(n_boresights=20_000, batch_chunk=100)),
    "rpnet": (3.0, lambda: js.Camera.from_fov(1024, 1024, 60.0, mag_limit=3.0), _rpnet_config),
    "pyramid": (5.5, lambda: js.camera_preset("mlv2021"), lambda: js.algorithms.get("pyramid").Config()),
}

# Smallest share of noise-free scenes an algorithm must identify (strict criterion); 1.0 unless
# listed. RpNet's world trains its network for seconds (200 + 200 steps): it names 11 and 10 of the
# 12 scenes with Config() and Config.paper() (the trained quick network identifies every scene of
# bench_rpnet.py on its own camera: experiments/RESULTS.md).
NOISE_FREE_RATE = {"rpnet": 0.8}


@dataclasses.dataclass
class World:
    algo: object
    catalog: object
    camera: object
    config: object
    database: object


_WORLDS: dict[str, World] = {}


def world(name: str) -> World:
    """The algorithm's world, its database built once per test process."""
    if name not in _WORLDS:
        algo = js.algorithms.get(name)
        limit, camera, config = WORLDS.get(name, (6.0, lambda: js.camera_preset("sgm2022"),
                                                  lambda: algo.Config()))
        catalog, camera, config = js.load_catalog(limit), camera(), config()
        database = algo.build_database(catalog, camera, config, progress=False)
        _WORLDS[name] = World(algo, catalog, camera, config, database)
    return _WORLDS[name]


def _paper(w: World):
    """The world's config with the settings ``Config.paper()`` changes from ``Config()``."""
    return base.paper_algorithm(w.config)


# Every scene of this file has one capacity (the clean scenes', packed ones too), so each algorithm
# compiles its kernels for one scene width here (RpNet compiles its network kernel per width); the
# width of test_rpnet.py's scenes and test_engine.py's, so the suite's program store serves those
# files the programs compiled here (or the other way round).
CAPACITY = 64


def _clean_scenes(w: World, n: int, seed: int):
    rows = np.random.default_rng(seed).choice(len(w.catalog), n, replace=False)
    return js.simulate(jax.random.key(seed), w.catalog, w.camera, js.NoiseConfig(), capacity=CAPACITY,
                       boresight_ids=rows)


def _random_point_scenes(w: World, n: int, n_points: int, seed: int):
    """Scenes of uniformly random points (no star pattern behind them): truth −1 everywhere."""
    rng = np.random.default_rng(seed)
    size = np.array([w.camera.width - 1, w.camera.height - 1])
    xy = [rng.uniform(0, 1, (n_points, 2)) * size for _ in range(n)]
    mag = [np.sort(rng.uniform(1.0, w.catalog.mag_limit, n_points)) for _ in range(n)]
    return js.scenes_from_centroids(xy, mag, capacity=CAPACITY)


@pytest.mark.parametrize("name", NAMES)
def test_module_offers_the_contract(name):
    """Names, signatures, config presets, the Tuning tuple and a pytree database with a cache key."""
    w = world(name)
    base.check_algorithm(w.algo, name)
    assert hash(w.config) == hash(dataclasses.replace(w.config))  # frozen, hashable
    paper = w.algo.Config.paper()
    assert isinstance(paper, w.algo.Config)
    tuning = w.config.tuning()
    assert isinstance(tuning, w.algo.Tuning) and isinstance(tuning, tuple)
    assert isinstance(w.config.database_fields(), dict)
    key = w.database.cache_key()
    assert isinstance(key, str) and len(key) == 20
    again = w.algo.build_database(w.catalog, w.camera, w.config, progress=False)  # from the cache
    assert again.cache_key() == key
    leaves, treedef = jax.tree.flatten(w.database)
    assert type(jax.tree.unflatten(treedef, leaves)) is type(w.database)


@pytest.mark.parametrize("name", NAMES)
def test_noise_free_scenes_are_identified(name):
    """Noise-free scenes: identified (strict: ≥ 3 correct, none wrong; see :data:`NOISE_FREE_RATE`),
    none wrong — with ``Config()`` and with ``Config.paper()``; diagnostics have the contract's
    shapes."""
    w = world(name)
    scenes = _clean_scenes(w, 12, seed=1)
    for config in (w.config, _paper(w)):
        result, diag = w.algo.identify(w.database, scenes, config, diagnostics=True)
        report = js.evaluate(scenes, result, "strict")
        assert report["misid_rate"] == 0.0, (name, config)
        assert report["identification_rate"] >= NOISE_FREE_RATE.get(name, 1.0), (name, report)
        assert np.shape(diag.n_candidates) == (12,) and np.shape(diag.overflow) == (12,)
        assert np.issubdtype(np.asarray(diag.n_candidates).dtype, np.integer)
        assert np.asarray(diag.overflow).dtype == bool
        assert np.all(np.asarray(diag.n_candidates) >= 0)
    if result.attitude is not None:
        ok = np.asarray(result.ok)
        err = np.asarray(js.attitude_errors_arcsec(result.attitude, scenes.attitude)[0])[ok]
        assert np.all(err < 60.0), err


@pytest.mark.parametrize("name", NAMES)
def test_random_points_and_false_stars_are_never_claimed(name):
    """Scenes with no star pattern (random points) and scenes of false stars only: never ``ok``, no id."""
    w = world(name)
    random_points = _random_point_scenes(w, 8, 15, seed=2)
    for scenes in (random_points, random_points[:4]):
        result = w.algo.identify(w.database, scenes, w.config)
        assert not np.any(np.asarray(result.ok)), name
        assert np.all(np.asarray(result.ids) == -1), name


@pytest.mark.parametrize("name", NAMES)
def test_batch_equals_per_scene(name):
    """Identifying a batch gives each scene what identifying it alone gives."""
    w = world(name)
    noise = js.NoiseConfig(position_sigma_px=0.5, n_false=1)
    rows = np.random.default_rng(3).choice(len(w.catalog), 4, replace=False)
    scenes = js.simulate(jax.random.key(3), w.catalog, w.camera, noise, capacity=CAPACITY,
                         boresight_ids=rows)
    batch = w.algo.identify(w.database, scenes, w.config)
    for i in range(scenes.batch_size):
        one = w.algo.identify(w.database, scenes[i], w.config)
        np.testing.assert_array_equal(np.asarray(one.ids)[0], np.asarray(batch.ids)[i])
        assert bool(np.asarray(one.ok)[0]) == bool(np.asarray(batch.ok)[i])
        if batch.attitude is not None and bool(np.asarray(batch.ok)[i]):
            np.testing.assert_allclose(np.asarray(one.attitude)[0], np.asarray(batch.attitude)[i],
                                       atol=1e-5)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.filterwarnings("ignore:.*the hypothesis search found more hypotheses")  # 120 random points
def test_overflow_is_flagged(name):
    """A scene packed with more detections than its capacity reports ``overflow`` in the diagnostics."""
    w = world(name)
    scenes = _clean_scenes(w, 2, seed=4)
    rng = np.random.default_rng(4)
    size = np.array([w.camera.width - 1, w.camera.height - 1])
    xy, mag = [], []
    for i in range(2):  # the scene's stars and faint random points, more than the capacity holds
        valid = np.asarray(scenes.valid[i])
        extra = CAPACITY + 8 - int(valid.sum())
        xy.append(np.concatenate([np.asarray(scenes.xy[i])[valid], rng.uniform(0, 1, (extra, 2)) * size]))
        faint = np.full(extra, w.catalog.mag_limit + 1.0)
        mag.append(np.concatenate([np.asarray(scenes.mag[i])[valid], faint]))
    packed = js.scenes_from_centroids(xy, mag, capacity=CAPACITY)
    assert np.all(np.asarray(packed.overflow))
    result, diag = w.algo.identify(w.database, packed, w.config, diagnostics=True)
    assert np.all(np.asarray(diag.overflow)), name
    assert np.asarray(result.ids).shape == (2, CAPACITY)


@pytest.mark.parametrize("name", NAMES)
def test_degenerate_scenes_fail_cleanly(name):
    """Empty scenes and scenes of one or two detections: a clean failure, not an error."""
    w = world(name)
    centre = np.array([[w.camera.cx, w.camera.cy]])
    xy = [np.zeros((0, 2)), centre, np.concatenate([centre, centre + 40.0])]
    scenes = js.scenes_from_centroids(xy, None, capacity=CAPACITY)
    result = w.algo.identify(w.database, scenes, w.config)
    assert not np.any(np.asarray(result.ok))
    assert np.all(np.asarray(result.ids) == -1)


@pytest.mark.parametrize("name", NAMES)
def test_bad_inputs_give_clear_errors(name):
    """Not a Scene, inconsistent shapes, NaN centroids: a ``TypeError``/``ValueError`` up front."""
    w = world(name)
    scenes = _clean_scenes(w, 2, seed=5)
    with pytest.raises(TypeError, match="Scene"):
        w.algo.identify(w.database, np.asarray(scenes.xy), w.config)
    with pytest.raises(ValueError, match="shapes"):
        w.algo.identify(w.database, dataclasses.replace(scenes, mag=scenes.mag[:, :3]), w.config)
    with pytest.raises(ValueError, match="NaN"):
        w.algo.identify(w.database, dataclasses.replace(scenes, xy=scenes.xy.at[0, 0, 0].set(jnp.nan)),
                        w.config)


# op-by-op execution of a whole identification takes 1–2 min per scene for the real algorithms on
# 2 cores: those run with the slow tests (`pytest -m slow`)
_EAGER_FAST = {"oracle"}


@pytest.mark.parametrize("name", [n if n in _EAGER_FAST else pytest.param(n, marks=pytest.mark.slow)
                                  for n in NAMES])
def test_jit_equals_no_jit(name):
    """The compiled kernels give what the same code gives run op by op (``jax.disable_jit``)."""
    w = world(name)
    scenes = _clean_scenes(w, 1, seed=6)
    compiled = w.algo.identify(w.database, scenes, w.config)
    with jax.disable_jit():
        eager = w.algo.identify(w.database, scenes, w.config)
    np.testing.assert_array_equal(np.asarray(eager.ids), np.asarray(compiled.ids))
    np.testing.assert_array_equal(np.asarray(eager.ok), np.asarray(compiled.ok))
    if compiled.attitude is not None and bool(np.asarray(compiled.ok)[0]):
        np.testing.assert_allclose(np.asarray(eager.attitude), np.asarray(compiled.attitude), atol=1e-5)


@pytest.mark.parametrize("name", NAMES)
def test_a_batch_of_zero_scenes_gives_an_empty_result(name):
    w = world(name)
    scenes = _clean_scenes(w, 2, seed=3)[0:0]
    result = w.algo.identify(w.database, scenes, w.config)
    assert np.shape(result.ids) == (0, scenes.capacity) and np.shape(result.ok) == (0,)


# --- optional hooks: declared in base.HOOKS with a default, read only through base ----------------


@pytest.mark.parametrize("name", NAMES)
def test_every_hook_answers_with_its_declared_kind(name):
    """Each reader of :mod:`~jstarid.algorithms.base` gives what the hook declares, whether the
    algorithm declares the hook or leaves it to the default."""
    w = world(name)
    algo = w.algo
    fields = {f.name for f in dataclasses.fields(algo.Config)}
    # the world's database is built and cached: a first_use must not ask to build it again
    assert base.first_use(algo, w.catalog, w.camera, w.config) is None, name
    other = dataclasses.replace(w.camera, f_px=w.camera.f_px * 1.001)  # another cache key
    planned = base.first_use(algo, w.catalog, other, w.config)
    assert planned is None or (isinstance(planned, tuple) and isinstance(planned[0], str)
                               and float(planned[1]) > 0), (name, planned)
    assert base.camera_problem(algo, w.camera, w.config, w.catalog) is None  # the world works
    assert isinstance(base.config_for_camera(algo, w.camera), algo.Config)
    presets = base.presets(algo)
    for preset, settings in presets.items():
        config = base.default_config(algo, w.camera, preset=preset)
        assert isinstance(config, algo.Config) and set(settings) <= fields
        assert all(getattr(config, k) == v for k, v in settings.items()), (name, preset)
    assert base.default_config(algo) == base.default_config(algo, preset=next(iter(presets), None))
    settings = base.frame_settings(algo)
    framed = base.default_config(algo, w.camera, frames=True)
    assert {k.split(".")[0] for k in settings} <= fields
    assert all(value_at(framed, k) == v for k, v in settings.items()), (name, settings)
    reported = base.reported(algo)
    assert set(reported) <= fields and all(len(v) >= 1 for v in reported.values())
    assert base.scoring_radius_deg(w.config) > 0
    info = base.database_info(w.database)
    assert isinstance(info, dict) and isinstance(info.get("cache_path", ""), str)
    assert base.first_compile_seconds(algo) > 0
    assert set(base.HOOKS) >= {h for h in base.HOOKS if base.declares(algo, h)}


@pytest.mark.parametrize("name", NAMES)
def test_identify_grid_gives_what_identify_gives(name):
    """The grid reader (the algorithm's own ``identify_grid`` or the default, one call per config)
    gives each config what ``identify`` gives it."""
    w = world(name)
    scenes = _clean_scenes(w, 2, seed=7)
    alone = w.algo.identify(w.database, scenes, w.config)
    results = base.identify_grid(w.algo, w.database, scenes, [w.config, w.config])
    assert len(results) == 2
    for result in results:
        np.testing.assert_array_equal(np.asarray(result.ids), np.asarray(alone.ids))
        np.testing.assert_array_equal(np.asarray(result.ok), np.asarray(alone.ok))


@pytest.mark.parametrize("name", NAMES)
def test_identify_takes_the_configs_tuning(name):
    """One ``identify`` signature everywhere: ``tuning=config.tuning()`` gives what the config
    alone gives."""
    w = world(name)
    scenes = _clean_scenes(w, 2, seed=9)
    alone = w.algo.identify(w.database, scenes, w.config)
    tuned = w.algo.identify(w.database, scenes, w.config, tuning=w.config.tuning())
    np.testing.assert_array_equal(np.asarray(tuned.ids), np.asarray(alone.ids))
    np.testing.assert_array_equal(np.asarray(tuned.ok), np.asarray(alone.ok))


class _Tuning(NamedTuple):
    """Nothing to sweep."""


@dataclasses.dataclass(frozen=True)
class _Config:
    seed: int = 0

    @classmethod
    def paper(cls, **overrides):
        return cls(**overrides)

    def tuning(self) -> _Tuning:
        return _Tuning()

    def database_fields(self) -> dict:
        return {}


@functools.partial(jax.tree_util.register_dataclass, data_fields=[], meta_fields=["key"])
@dataclasses.dataclass(frozen=True)
class _Database:
    key: str = ""

    def cache_key(self) -> str:
        return self.key


class _Diagnostics(NamedTuple):
    n_candidates: jax.Array
    overflow: jax.Array


def _build_database(catalog, camera, config=None, *, use_cache=True, progress=True):
    return _Database(key=base.cache_key("hookless", 1, catalog, camera, {}))


def _identify(database, scenes, config=None, *, tuning=None, diagnostics=False):
    """The truth of every detection (as the oracle)."""
    base.check_scenes(scenes)
    ids = jnp.where(scenes.valid, scenes.truth, -1).astype(jnp.int32)
    result = js.Identification(ids=ids, ok=jnp.any(ids >= 0, axis=1), attitude=None)
    if diagnostics:
        return result, _Diagnostics(jnp.zeros(scenes.batch_size, jnp.int32), scenes.overflow)
    return result


def _hookless_module() -> types.ModuleType:
    """A minimal algorithm: the six required names and none of the optional hooks."""
    module = types.ModuleType("hookless_algorithm")
    module.__spec__ = importlib.machinery.ModuleSpec("hookless_algorithm", None)  # importable
    module.Config, module.Tuning, module.Database = _Config, _Tuning, _Database
    module.Diagnostics = _Diagnostics
    module.build_database, module.identify = _build_database, _identify
    return module


def test_an_algorithm_without_optional_hooks_runs_through_the_defaults(monkeypatch):
    """Every hook's default, through the readers and through the engine (a grid run config by
    config, the plan, the camera check)."""
    fake = base.check_algorithm(_hookless_module(), "hookless")
    assert not any(base.declares(fake, hook) for hook in base.HOOKS)
    cat, cam = js.load_catalog(5.0), js.camera_preset("sgm2022")
    config = fake.Config()
    assert base.first_use(fake, cat, cam, config) is None
    assert base.camera_problem(fake, cam, config, cat) is None
    assert base.reported(fake) == {} and base.presets(fake) == {} and base.frame_settings(fake) == {}
    assert base.config_for_camera(fake, cam, seed=3) == fake.Config(seed=3)
    # a preset named for other algorithms is ignored by one without presets
    assert base.default_config(fake, cam, preset="quick", frames=True) == config
    assert base.scoring_radius_deg(config) == base.DEFAULT_RADIUS_DEG
    assert base.first_compile_seconds(fake) == base.DEFAULT_FIRST_COMPILE_SECONDS
    database = fake.build_database(cat, cam, config)
    assert base.database_info(database) == {}
    scenes = js.simulate(jax.random.key(8), cat, cam, js.NoiseConfig(), batch_size=3, capacity=32)
    results = base.identify_grid(fake, database, scenes, [config, fake.Config(seed=1)])
    assert len(results) == 2
    for result in results:
        np.testing.assert_array_equal(np.asarray(result.ids), np.asarray(fake.identify(database, scenes).ids))
    # registered, it runs in the engine on the defaults alone
    monkeypatch.setitem(sys.modules, "hookless_algorithm", fake)
    monkeypatch.setattr(js.algorithms, "_REGISTRY", dict(js.algorithms._REGISTRY))  # undone after
    js.algorithms.register("hookless", "hookless_algorithm")
    assert js.engine.default_config("hookless", camera=cam, frames=True) == config
    assert js.engine.plan("hookless", cat, cam) == []
    assert js.engine.plan("hookless", cat, cam, compiled_before=False) == [
        ("compiled kernels, kept on disk for later runs", base.DEFAULT_FIRST_COMPILE_SECONDS)]
    result = js.compare(scenes, [js.grid("hookless", seed=[0, 1])], cat, cam, progress=False)
    assert [row["identification_rate"] for row in result.rows()] == [1.0, 1.0]


def test_check_algorithm_refuses_hooks_of_the_wrong_kind():
    for hook, value, message in (("PRESETS", 3, "PRESETS must be a mapping"),
                                 ("PRESETS", {"fast": 1}, r"PRESETS\['fast'\]"),
                                 ("first_use", "soon", "first_use must be a function"),
                                 ("REPORTED", ["seed"], "REPORTED must be a mapping")):
        fake = _hookless_module()
        setattr(fake, hook, value)
        with pytest.raises(TypeError, match=message):
            base.check_algorithm(fake, "hookless")
    fake = _hookless_module()
    fake.build_database = lambda catalog, camera, config=None, *, progress=True: None
    with pytest.raises(TypeError, match="use_cache"):
        base.check_algorithm(fake, "hookless")
    with pytest.raises(ValueError, match="rpnet has no preset 'huge'; presets: quick, table3"):
        base.default_config(js.algorithms.get("rpnet"), preset="huge")


def test_hooks_are_read_only_through_the_contract():
    """The contract imports nothing above it, and the engine and the CLI neither look hooks up by
    name nor name an algorithm in a comparison."""
    package = Path(base.__file__).resolve().parents[1]
    tree = ast.parse((package / "algorithms" / "base.py").read_text())
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {a.name for node in ast.walk(tree) if isinstance(node, ast.Import) for a in node.names}
    above = ("jstarid.experiment", "jstarid.engine", "jstarid.cli")
    assert not {m for m in imported if m and m.startswith(above)}
    hooks = "|".join(base.HOOKS)
    names = "|".join(NAMES)
    for path in sorted((package / "engine").glob("*.py")) + sorted((package / "cli").glob("*.py")):
        text = path.read_text()
        assert not re.search(rf"(getattr|hasattr)\([^\n]*?[\"']({hooks})[\"']", text), path.name
        assert not re.search(rf"(==|!=|\bin)\s*[\"']({names})[\"']|[\"']({names})[\"']\s*(==|!=|\bin\b)",
                             text), path.name
