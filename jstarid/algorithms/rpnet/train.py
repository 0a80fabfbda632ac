"""RpNet training in two stages (§II-D, Fig. 5).

Stage 1 trains the pattern generation network, a denoising autoencoder (generator + decoder), on
(noisy input → clean input) with the MSE loss of eq. 5. Stage 2 freezes the generator and trains the
classifier on its codes of noisy inputs with the cross-entropy of eq. 6. Both stages draw fresh
batches from :func:`~jstarid.algorithms.rpnet.data.make_batch` at every step (the paper's 320 noise
samples per guide star become an endless stream of them); a held-out batch from a separate key gives
the progress-bar metrics and the classifier's early stopping.

The model variables are one dict ``{"generator": …, "decoder": …, "classifier": {"params": …,
"batch_stats": …}}`` of arrays. :func:`checkpoint_meta` gives the fingerprints (catalog, camera,
network-shaping config, guide list) that every checkpoint and snapshot carries (:mod:`.checkpoint`).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from jstarid.algorithms.rpnet.checkpoint import Snapshot, load_snapshot, save_snapshot
from jstarid.algorithms.rpnet.config import Config
from jstarid.algorithms.rpnet.data import FAMILIES, build_tables, make_batch
from jstarid.algorithms.rpnet.model import (
    Classifier,
    Decoder,
    Generator,
    bf16_dot_general,
    ce_loss,
    l2_penalty,
    mse_loss,
)
from jstarid.runtime.prefetch import prefetch

__all__ = ["batch_source", "checkpoint_meta", "clf_learning_rate", "clf_loss_fn", "dae_loss_fn",
           "init_variables", "predict_logits", "train"]


def _modules(config: Config, n_classes: int, dot_general=None):
    gen = Generator(widths=tuple(config.gen_widths), dot_general=dot_general)
    dec = Decoder(hidden=config.gen_widths[0], n_out=config.input_size)
    clf = Classifier(n_classes=n_classes, hidden=config.clf_width, dot_general=dot_general)
    return gen, dec, clf


def init_variables(key, config: Config, n_classes: int) -> dict:
    """Freshly initialised variables of the three networks (shapes of Tables 1–2)."""
    gen, dec, clf = _modules(config, n_classes)
    k1, k2, k3 = jax.random.split(key, 3)
    x = jnp.zeros((1, config.input_size), jnp.float32)
    z = jnp.zeros((1, config.gen_widths[1]), jnp.float32)
    c = clf.init(k3, z, train=False)
    return {"generator": gen.init(k1, x)["params"], "decoder": dec.init(k2, z)["params"],
            "classifier": {"params": c["params"], "batch_stats": c["batch_stats"]}}


@functools.partial(jax.jit, static_argnames=("config", "n_classes", "bf16"))
def predict_logits(variables, inputs, *, config: Config, n_classes: int, bf16: bool = False):
    """(..., 2⌊ρ/e⌋) initial inputs → (..., K) float32 logits (generator, then classifier, inference mode).

    ``bf16``: matmuls on bfloat16 operands with float32 accumulation (:func:`bf16_dot_general`;
    ``Config.network_bf16`` at identification); training and its held-out metrics use float32.
    """
    gen, _, clf = _modules(config, n_classes, bf16_dot_general if bf16 else None)
    z = gen.apply({"params": variables["generator"]}, inputs)
    return clf.apply(variables["classifier"], z, train=False)


def dae_loss_fn(config: Config, n_classes: int):
    """Stage-1 loss ``(params, noisy, clean) → (MSE + L2, MSE)`` (eq. 5); params: generator + decoder."""
    gen, dec, _ = _modules(config, n_classes)
    l2 = config.training.l2

    def loss_fn(params, noisy, clean):
        z = gen.apply({"params": params["generator"]}, noisy)
        rec = dec.apply({"params": params["decoder"]}, z)
        mse = mse_loss(clean, rec)  # eq. 5
        return mse + l2 * l2_penalty(params), mse

    return loss_fn


def clf_loss_fn(config: Config, n_classes: int):
    """Stage-2 loss ``(params, batch_stats, gen_params, noisy, label) → (CE + L2, (CE, batch_stats))``
    (eq. 6) on the frozen generator's codes, BatchNorm in training mode."""
    gen, _, clf = _modules(config, n_classes)
    l2 = config.training.l2

    def loss_fn(params, batch_stats, gen_params, noisy, label):
        z = gen.apply({"params": gen_params}, noisy)  # frozen generator: no gradient reaches it
        logits, new_state = clf.apply({"params": params, "batch_stats": batch_stats}, z, train=True,
                                      mutable=["batch_stats"])
        ce = ce_loss(logits, label)  # eq. 6
        return ce + l2 * l2_penalty(params), (ce, new_state["batch_stats"])

    return loss_fn


def batch_source(catalog, camera, config: Config, tables, key):
    """``next_batch(stage_key, step)``: the training batch of a step (drawn on the fly from
    ``fold_in(stage_key, step)``, or cycled from a pool drawn once from ``key`` with
    ``Training.pool_batches``)."""
    t = config.training
    if t.pool_batches:  # pool mode: n batches drawn once, cycled through by both stages
        k_pool = jax.random.fold_in(key, 10**9)
        pool = [make_batch(jax.random.fold_in(k_pool, i), catalog, camera, config, tables, t.batch_size)
                for i in range(t.pool_batches)]

    def next_batch(k, s):
        if t.pool_batches:
            return pool[s % t.pool_batches]
        return make_batch(jax.random.fold_in(k, s), catalog, camera, config, tables, t.batch_size)

    return next_batch


def _make_dae_step(config: Config, n_classes: int, tx):
    loss_fn = dae_loss_fn(config, n_classes)

    @jax.jit
    def step(params, opt_state, noisy, clean):
        (_, mse), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, noisy, clean)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, mse

    @jax.jit
    def evaluate(params, noisy, clean):
        return loss_fn(params, noisy, clean)[1]

    return step, evaluate


def _make_clf_step(config: Config, n_classes: int, tx):
    loss_fn = clf_loss_fn(config, n_classes)

    @jax.jit
    def step(params, batch_stats, opt_state, gen_params, noisy, label):
        (_, (ce, batch_stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, batch_stats, gen_params, noisy, label)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), batch_stats, opt_state, ce

    return step


def clf_learning_rate(t, clf_steps: int):
    """Stage 2's learning rate: ``t.clf_lr``, with cosine decay to 1 % over ``clf_steps`` (Table 3)."""
    return (optax.cosine_decay_schedule(t.clf_lr, max(clf_steps, 1), alpha=0.01) if t.clf_lr_decay
            else t.clf_lr)


def _accuracy(variables, batch, config, n_classes) -> tuple[float, dict[str, float]]:
    pred = jnp.argmax(predict_logits(variables, batch.noisy, config=config, n_classes=n_classes), -1)
    hit = np.asarray(pred == batch.label)
    fam = np.asarray(batch.family)
    return float(hit.mean()), {name: float(hit[fam == i].mean()) for i, name in enumerate(FAMILIES)}


def train(catalog, camera, config: Config, guide_rows, *, progress: bool = True, variables=None,
          snapshot_path=None, snapshot_every: int = 500) -> tuple[dict, dict]:
    """Train RpNet (both stages) for ``config.training``.

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` with a V 7.0 simulation list.
        camera: :class:`~jstarid.camera.Camera` of the training scenes.
        config: :class:`Config`; ``config.training`` sets steps, rates, batch size, seed.
        guide_rows: (K,) catalog rows of the classes.
        progress: show tqdm progress bars (loss, held-out metrics).
        variables: start from these variables instead of a fresh initialisation.
        snapshot_path: optional file for training snapshots (:mod:`.checkpoint`): written every
            ``snapshot_every`` steps of each stage and at the end of stage 1; when it exists at
            the start, training resumes from it (same result as an uninterrupted run). The caller
            deletes it once the final checkpoint is safe.
        snapshot_every: steps between snapshots.

    Returns:
        ``(variables, history)``; history holds the per-step losses and held-out metrics.

    Raises:
        ValueError: ``snapshot_path`` holds a snapshot of another catalog, camera or config.
    """
    t = config.training
    n_classes = int(len(guide_rows))
    tables = build_tables(catalog, camera, config, guide_rows)
    key = jax.random.key(t.seed)
    k_init, k_eval, k_dae, k_clf = jax.random.split(key, 4)
    if variables is None:
        variables = init_variables(k_init, config, n_classes)
    meta = checkpoint_meta(catalog, camera, config, guide_rows)
    snapshot_every = max(1, int(snapshot_every))
    held_out = make_batch(k_eval, catalog, camera, config, tables, t.eval_size)
    dae_steps, clf_steps = t.steps(n_classes)
    next_batch = batch_source(catalog, camera, config, tables, k_dae)
    history: dict = {"dae_loss": [], "dae_eval": [], "clf_loss": [], "clf_eval": []}
    tx_dae = optax.adam(t.dae_lr)  # stage 1: Adam at the PGN rate, no rate decay
    # stage 2: cosine rate decay and early stop (Table 3)
    tx_clf = optax.adam(clf_learning_rate(t, clf_steps))
    resume = None
    if snapshot_path is not None and Path(snapshot_path).exists():
        resume = load_snapshot(snapshot_path, meta, variables, lambda stage: (
            tx_dae.init({"generator": variables["generator"], "decoder": variables["decoder"]})
            if stage == 1 else tx_clf.init(variables["classifier"]["params"])))
        variables, history = resume.variables, resume.history

    def snapshot(stage, step, opt_state, best=(-1.0, None)):
        if snapshot_path is not None:
            save_snapshot(snapshot_path, Snapshot(stage, step, variables, opt_state, best[0], best[1],
                                                  history), meta)

    # Stage 1: denoising autoencoder (eq. 5).
    dae_params = {"generator": variables["generator"], "decoder": variables["decoder"]}
    opt_state = resume.opt_state if resume is not None and resume.stage == 1 else tx_dae.init(dae_params)
    start = 0 if resume is None else (resume.step if resume.stage == 1 else dae_steps)
    dae_step, dae_eval = _make_dae_step(config, n_classes, tx_dae)
    bar = tqdm(range(start, dae_steps), desc="RpNet stage 1 (DAE)", disable=not progress, initial=start,
               total=dae_steps)
    batches = prefetch(functools.partial(next_batch, k_dae), range(start, dae_steps))
    with contextlib.closing(batches):
        for s, batch in zip(bar, batches, strict=True):
            dae_params, opt_state, mse = dae_step(dae_params, opt_state, batch.noisy, batch.clean)
            history["dae_loss"].append(float(mse))
            if (s + 1) % t.eval_every == 0 or s + 1 == dae_steps:
                ev = float(dae_eval(dae_params, held_out.noisy, held_out.clean))
                history["dae_eval"].append((s + 1, ev))
                bar.set_postfix(mse=f"{history['dae_loss'][-1]:.4f}", held_out=f"{ev:.4f}")
            if (s + 1) % snapshot_every == 0 and s + 1 < dae_steps:
                variables = {**variables, **dae_params}
                snapshot(1, s + 1, opt_state)
    variables = {**variables, **dae_params}

    # Stage 2: classifier on frozen generator codes (eq. 6).
    clf_params = variables["classifier"]["params"]
    batch_stats = variables["classifier"]["batch_stats"]
    clf_step = _make_clf_step(config, n_classes, tx_clf)
    if resume is not None and resume.stage == 2:
        opt_state, start = resume.opt_state, resume.step
        best = (resume.best_accuracy, resume.best if resume.best is not None else variables["classifier"])
    else:
        opt_state, start = tx_clf.init(clf_params), 0
        best = (-1.0, variables["classifier"])
        if dae_steps > 0:
            snapshot(2, 0, opt_state, best)  # stage 1 is safe from here on
    bar = tqdm(range(start, clf_steps), desc="RpNet stage 2 (classifier)", disable=not progress,
               initial=start, total=clf_steps)
    batches = prefetch(functools.partial(next_batch, k_clf), range(start, clf_steps))
    with contextlib.closing(batches):
        for s, batch in zip(bar, batches, strict=True):
            clf_params, batch_stats, opt_state, ce = clf_step(clf_params, batch_stats, opt_state,
                                                             variables["generator"], batch.noisy, batch.label)
            history["clf_loss"].append(float(ce))
            if (s + 1) % t.eval_every == 0 or s + 1 == clf_steps:
                current = {"params": clf_params, "batch_stats": batch_stats}
                acc, per_family = _accuracy({**variables, "classifier": current}, held_out, config, n_classes)
                history["clf_eval"].append((s + 1, acc, per_family))
                if acc > best[0] or not t.early_stop:
                    best = (acc, current)
                bar.set_postfix(ce=f"{history['clf_loss'][-1]:.3f}", held_out_acc=f"{acc:.3f}")
            if (s + 1) % snapshot_every == 0 and s + 1 < clf_steps:
                variables = {**variables, "classifier": {"params": clf_params, "batch_stats": batch_stats}}
                snapshot(2, s + 1, opt_state, best)
    if clf_steps == 0:
        best = (-1.0, {"params": clf_params, "batch_stats": batch_stats})
    variables = {**variables, "classifier": best[1]}
    history["best_held_out_accuracy"] = best[0]
    return variables, history


def checkpoint_meta(catalog, camera, config: Config, guide_rows) -> dict[str, str]:
    """What a checkpoint is tied to: catalog, camera and config fingerprints, and the class list."""
    cam = camera.database_fields()
    rows = np.ascontiguousarray(np.asarray(guide_rows, np.int32))
    return {
        "catalog": catalog.fingerprint,
        "camera": hashlib.sha256(json.dumps(cam, sort_keys=True).encode()).hexdigest()[:16],
        "config": config.fingerprint(),
        "guides": hashlib.sha256(rows.tobytes()).hexdigest()[:16],
        "n_classes": str(len(rows)),
    }
