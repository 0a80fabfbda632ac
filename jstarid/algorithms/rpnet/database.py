"""The RpNet "database": guide catalog + trained networks for a (catalog, camera, config), cached.

RpNet stores no patterns: its database is the network (§III-C). :func:`build_database` selects the
guide stars, then loads the checkpoint cached for this catalog, camera and network-shaping config or,
when there is none, trains one (:func:`~jstarid.algorithms.rpnet.train.train`) and caches it under
``jstarid.catalog.cache_dir() / "rpnet"``.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.base import cache_key
from jstarid.algorithms.rpnet.checkpoint import load_checkpoint, save_checkpoint
from jstarid.algorithms.rpnet.config import Config, Training
from jstarid.algorithms.rpnet.guide_catalog import guide_rows
from jstarid.algorithms.rpnet.inference import InferenceWeights, fold_networks
from jstarid.algorithms.rpnet.train import (
    checkpoint_meta,
    init_variables,
    train,
)
from jstarid.catalog import cache_dir, load_or_build
from jstarid.runtime import device_cache

__all__ = ["PRESETS", "Database", "build_database", "checkpoint_path", "database_from_variables",
           "database_key", "load_database"]

#: The networks a sweep or a command chooses by name (``--rpnet-network``;
#: :func:`jstarid.algorithms.base.default_config`). ``Config()`` trains the paper's Table 3 schedule
#: (about 2 hours on 2 CPU cores), so the first, the default, is the ``quick`` one (about 5 minutes).
PRESETS = {"quick": {"training": Training.quick()}, "table3": {"training": Training()}}
# A network that classifies fewer held-out patterns than this has learned next to nothing (a sparse
# field's guides, whose patterns hold a handful of neighbours): build_database says so.
MIN_HELD_OUT_ACCURACY = 0.05


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["guide_rows", "star_vectors", "star_mags", "variables"],
                   meta_fields=["config", "camera", "catalog_fingerprint", "history", "path", "key"])
@dataclasses.dataclass(frozen=True, eq=False)
class Database:
    """Everything :func:`~jstarid.algorithms.rpnet.identify` needs (a pytree: the class list, the
    star vectors and the network variables are its leaves).

    Attributes:
        config: the :class:`Config` the networks were trained for.
        camera: the :class:`~jstarid.camera.Camera` of the training scenes.
        catalog_fingerprint: the catalog's fingerprint (ids are its rows).
        guide_rows: (K,) int32 catalog row of each class.
        star_vectors: (N, 3) float32 ICRS unit vectors of the whole catalog (naming the other stars).
        star_mags: (N,) float32 their V magnitudes (the brightness test of the final check).
        variables: network variables (see :mod:`~jstarid.algorithms.rpnet.train`).
        history: training history when trained in this call, else ``None``.
        path: the checkpoint file, when cached.
        key: :meth:`cache_key`.
    """

    config: Config
    camera: object
    catalog_fingerprint: str
    guide_rows: np.ndarray
    star_vectors: jax.Array
    star_mags: jax.Array
    variables: dict
    history: dict | None = None
    path: Path | None = None
    key: str = ""

    def cache_key(self) -> str:
        """The database's cache key (:func:`jstarid.algorithms.base.cache_key`): catalog, camera and
        the network-shaping settings (``Config.database_fields()``)."""
        return self.key

    @property
    def n_classes(self) -> int:
        return int(len(self.guide_rows))

    def info_dict(self) -> dict:
        """``{"cache_path": the checkpoint file, "" when not cached}``."""
        return {"cache_path": str(self.path) if self.path else ""}

    @property
    def inference_weights(self) -> InferenceWeights:
        """The networks folded for identification (:func:`.inference.fold_networks`), computed once
        per database (kept in :data:`jstarid.runtime.device_cache`)."""
        return device_cache.cached(self, "rpnet_inference", lambda: fold_networks(self.variables))


_FORMAT = 1  # bump when the checkpoint's layout changes meaning


def database_key(catalog, camera, config: Config) -> str:
    """:func:`jstarid.algorithms.base.cache_key` of the networks for this catalog, camera, config."""
    return cache_key("rpnet", _FORMAT, catalog, camera, config.database_fields())


def checkpoint_path(catalog, camera, config: Config) -> Path:
    """Cache file of the checkpoint for this catalog, camera and network-shaping config."""
    return cache_dir() / "rpnet" / f"rpnet-{database_key(catalog, camera, config)}.msgpack"


def build_database(catalog, camera, config: Config | None = None, *, use_cache: bool = True,
                   progress: bool = True, train_if_missing: bool = True) -> Database:
    """Guide catalog + trained networks (loaded from the cache, or trained and cached).

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` (V 7.0 simulation list for magnitude noise).
        camera: :class:`~jstarid.camera.Camera`.
        config: :class:`Config` (default: paper); ``config.training`` sets the training run.
        use_cache: read / write the checkpoint under the cache directory (:func:`checkpoint_path`).
        progress: progress bars while training.
        train_if_missing: train when no checkpoint exists (else raise ``FileNotFoundError``). With
            ``use_cache``, training writes snapshots (``….partial.msgpack`` beside the checkpoint)
            and an interrupted training resumes from the last one.

    Returns:
        :class:`Database`.
    """
    config = Config() if config is None else config
    rows = guide_rows(catalog, config)
    meta = checkpoint_meta(catalog, camera, config, rows)
    path = checkpoint_path(catalog, camera, config)
    # with the cache, training leaves snapshots next to the checkpoint: an interrupted run resumes
    # where it stopped when called again
    snapshot = path.with_name(path.stem + ".partial.msgpack") if use_cache else None

    def trained() -> tuple[dict, dict]:
        if not train_if_missing:
            raise FileNotFoundError(f"no RpNet checkpoint at {path}; train with experiments/train_rpnet.py")
        return train(catalog, camera, config, rows, progress=progress, snapshot_path=snapshot)

    (variables, history), loaded = load_or_build(
        path if use_cache else None, trained,
        load=lambda file: (load_checkpoint(file, meta, _template(config, len(rows))), None),
        save=lambda file, built: save_checkpoint(file, built[0], meta))
    if use_cache and not loaded:
        snapshot.unlink(missing_ok=True)  # the checkpoint is written: nothing left to resume
    if not loaded:
        _say_if_untrained(history, camera)
    return _database(catalog, camera, config, rows, variables, history, path if use_cache else None)


def _say_if_untrained(history: dict, camera) -> None:
    """Warn where the training ended below :data:`MIN_HELD_OUT_ACCURACY` held-out accuracy."""
    accuracy = float(history.get("best_held_out_accuracy", 1.0))
    if accuracy < MIN_HELD_OUT_ACCURACY:
        warnings.warn(f"RpNet's network for camera {camera.name} classifies {accuracy:.1%} of held-out "
                      "patterns: it has learned next to nothing (a sparse field's guides have too few "
                      "neighbours within rho_deg to tell apart), so its identifications will be the "
                      "finishing stage's search (Finishing.hypotheses) alone", stacklevel=3)


def load_database(path, catalog, camera, config: Config | None = None) -> Database:
    """A :class:`Database` from an explicit checkpoint file (``ValueError`` if built for another setup)."""
    config = Config() if config is None else config
    rows = guide_rows(catalog, config)
    variables = load_checkpoint(path, checkpoint_meta(catalog, camera, config, rows),
                                _template(config, len(rows)))
    return _database(catalog, camera, config, rows, variables, None, Path(path))


def database_from_variables(catalog, camera, config: Config, variables: dict) -> Database:
    """A :class:`Database` around given network variables (one member of a training grid,
    :func:`~jstarid.algorithms.rpnet.grid.member_variables`); nothing is read or cached."""
    rows = guide_rows(catalog, config)
    expected = jax.eval_shape(lambda: init_variables(jax.random.key(0), config, len(rows)))
    if jax.tree.map(jnp.shape, variables) != jax.tree.map(lambda a: a.shape, expected):
        raise ValueError("variables do not have the shapes of this config's networks and guide catalog")
    return _database(catalog, camera, config, rows, variables, None, None)


def _template(config: Config, n_classes: int) -> dict:
    """Variables of the right structure for reading a checkpoint."""
    return init_variables(jax.random.key(0), config, n_classes)


def _database(catalog, camera, config, rows, variables, history, path) -> Database:
    return Database(config=config, camera=camera, catalog_fingerprint=catalog.fingerprint,
                    guide_rows=np.asarray(rows, np.int32),
                    star_vectors=jnp.asarray(catalog.unit_vectors, jnp.float32),
                    star_mags=jnp.asarray(catalog.mag, jnp.float32), variables=variables,
                    history=history, path=path, key=database_key(catalog, camera, config))


# Seconds per training step per 256 samples on a 2-core CPU: the data and the DAE, plus the
# classifier's last layer per million weights (hidden width × classes). Measured (Intel Xeon host,
# batches drawn in one compiled call, a step ahead): quick on tetra3_test (5,070 × 512 weights)
# DAE 25 ms, classifier 49 ms per step, built in 232 s; on the narrow twin (10,800 × 256) 28 and
# 54 ms, 257 s.
_SECONDS_PER_STEP_256 = 0.027
_SECONDS_PER_STEP_256_PER_MWEIGHT = 0.0095


def first_use(catalog, camera, config: Config | None = None) -> tuple[str, float] | None:
    """What :func:`build_database` will build for these settings and about how long the training
    takes on a 2-core CPU (s); ``None`` when a trained network is cached."""
    config = Config() if config is None else config
    if checkpoint_path(catalog, camera, config).exists():
        return None
    n_guides = len(guide_rows(catalog, config))
    dae, clf = config.training.steps(n_guides)
    weights_m = config.clf_width * n_guides / 1e6
    per_256 = _SECONDS_PER_STEP_256 * (dae + clf) + _SECONDS_PER_STEP_256_PER_MWEIGHT * weights_m * clf
    seconds = per_256 * config.training.batch_size / 256
    return (f"RpNet networks trained for {camera.name} ({dae + clf:,} steps, {n_guides:,} guide "
            f"stars; resumable)", seconds)
