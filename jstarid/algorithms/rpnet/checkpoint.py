"""RpNet checkpoints: one file format for trained networks and for resumable training snapshots.

Every file is a msgpack payload (``flax.serialization``) ``{"meta", "variables"[, "training"]}``.
``meta`` holds the fingerprints it was written for (catalog, camera, network config, guide list;
:func:`~jstarid.algorithms.rpnet.train.checkpoint_meta`; a snapshot adds the training schedule) and
is checked on every read: a file for another setup is an error, never used silently. A trained
network (:func:`save_checkpoint`) has ``variables`` only; a snapshot (:func:`save_snapshot`) adds
``training`` (stage, next step, optimizer state, early-stopping classifier, history), so a killed
long training resumes. Batches depend only on (key, step), so a resumed run draws the same batches
as an uninterrupted one and ends with the same variables.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np

from jstarid.catalog import temporary_path

__all__ = ["Snapshot", "load_checkpoint", "load_snapshot", "save_checkpoint", "save_snapshot"]


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """Training state at the start of step ``step`` of stage ``stage`` (1: DAE, 2: classifier).

    Attributes:
        stage: 1 or 2.
        step: the next step of that stage to run (0-based).
        variables: model variables (stage 1: generator and decoder being trained).
        opt_state: the stage's optax state.
        best_accuracy: stage 2: held-out accuracy of ``best`` (−1 before the first evaluation).
        best: stage 2: the classifier variables kept by early stopping (``None`` in stage 1).
        history: the training history so far.
    """

    stage: int
    step: int
    variables: dict
    opt_state: object
    best_accuracy: float
    best: dict | None
    history: dict


def _state(tree):
    return flax.serialization.to_state_dict(jax.tree_util.tree_map(np.asarray, tree))


def _restore(template, state):
    return jax.tree_util.tree_map(jnp.asarray, flax.serialization.from_state_dict(template, state))


def _write(path, meta: dict[str, str], variables: dict, training: dict | None = None) -> Path:
    """Write one checkpoint file (atomic rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"meta": dict(meta), "variables": _state(variables)}
    if training is not None:
        payload["training"] = training
    tmp = temporary_path(path)
    tmp.write_bytes(flax.serialization.msgpack_serialize(payload))
    tmp.replace(path)
    return path


def _read(path, meta: dict[str, str], what: str, remedy: str) -> dict:
    """The payload of a checkpoint file whose ``meta`` has every entry of ``meta``.

    Raises:
        ValueError: a fingerprint differs (the message names it and the ``remedy``).
        FileNotFoundError: no such file.
    """
    raw = flax.serialization.msgpack_restore(Path(path).read_bytes())
    saved = raw.get("meta", {})
    for name in sorted(meta):
        if saved.get(name) != meta[name]:
            raise ValueError(f"RpNet {what} {path} was written for another {name} "
                             f"({saved.get(name)!r}, expected {meta[name]!r}); {remedy}")
    return raw


def save_checkpoint(path, variables: dict, meta: dict[str, str]) -> Path:
    """Write trained ``variables`` with ``meta`` (:func:`~.train.checkpoint_meta`)."""
    return _write(path, meta, variables)


def load_checkpoint(path, meta: dict[str, str], template: dict) -> dict:
    """The variables of a checkpoint written for ``meta``, in the structure of ``template``.

    Raises:
        ValueError: the checkpoint belongs to another catalog, camera, config or guide list.
        FileNotFoundError: no such file.
    """
    raw = _read(path, meta, "checkpoint", "rebuild the database")
    return _restore(template, raw["variables"])


def save_snapshot(path, snap: Snapshot, meta: dict[str, str]) -> Path:
    """Write ``snap`` with ``meta`` (fingerprints and schedule) to ``path`` (atomic rename)."""
    training = {"stage": snap.stage, "step": snap.step, "opt_state": _state(snap.opt_state),
                "best_accuracy": float(snap.best_accuracy),
                "best": _state(snap.best) if snap.best is not None else {},
                "history": json.dumps(snap.history)}
    return _write(path, meta, snap.variables, training)


def load_snapshot(path, meta: dict[str, str], variables_template: dict, opt_state_template) -> Snapshot:
    """Read a snapshot written for ``meta``.

    Args:
        path: snapshot file.
        meta: the fingerprints and schedule of the run to resume; must equal the saved ones.
        variables_template: model variables of the right structure (e.g. a fresh initialisation).
        opt_state_template: function ``stage → optax state`` of the right structure for that stage.

    Returns:
        :class:`Snapshot`.

    Raises:
        ValueError: the snapshot belongs to another catalog, camera, config or schedule, or holds no
            training state.
    """
    raw = _read(path, meta, "training snapshot", "delete it to start over")
    if "training" not in raw:
        raise ValueError(f"RpNet training snapshot {path} holds no training state; delete it to start over")
    t = raw["training"]
    stage = int(t["stage"])
    variables = _restore(variables_template, raw["variables"])
    best = _restore(variables_template["classifier"], t["best"]) if t["best"] else None
    history = json.loads(t["history"])
    for name in ("dae_eval", "clf_eval"):  # JSON turned the (step, value, …) tuples into lists
        history[name] = [tuple(entry) for entry in history.get(name, [])]
    return Snapshot(stage=stage, step=int(t["step"]), variables=variables,
                    opt_state=_restore(opt_state_template(stage), t["opt_state"]),
                    best_accuracy=float(t["best_accuracy"]), best=best, history=history)
