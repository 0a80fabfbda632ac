"""Training grids: G RpNet models of one architecture trained side by side in one vmapped step.

Each member g has its own initialisation seed and stage-1 (DAE) and stage-2 (classifier) learning
rates; parameters and Adam moments carry a leading member axis, and one jit-compiled ``vmap`` step
updates all G on the same batch, drawn once per step (the data is shared by the grid; the small
networks become batched matrix products). A width grid is a loop over architectures.

Member g follows :func:`~jstarid.algorithms.rpnet.train.train` for ``Training(seed=seeds[g],
dae_lr=dae_lrs[g], clf_lr=clf_lrs[g])``, except that the data keys (training and held-out batches)
come from ``config.training.seed`` for every member, so all are compared on the same samples: a
member whose seed is that seed is the single :func:`train` run at its rates (tested, to float32
rounding). ``optax.inject_hyperparams(optax.adam)`` keeps each member's learning rate in its
optimiser state (stage 2 sets lr_g · the cosine factor every step). Each member keeps its best
held-out classifier (``Training.early_stop``).
"""

from __future__ import annotations

import dataclasses
import itertools
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from jstarid.algorithms.rpnet.config import Config
from jstarid.algorithms.rpnet.data import FAMILIES, build_tables, make_batch
from jstarid.algorithms.rpnet.train import (
    batch_source,
    clf_learning_rate,
    clf_loss_fn,
    dae_loss_fn,
    init_variables,
    predict_logits,
)

__all__ = ["GridResult", "grid_members", "member_variables", "train_grid"]


@dataclasses.dataclass(frozen=True)
class GridResult:
    """What :func:`train_grid` returns (G members, E evaluations per stage).

    Attributes:
        seeds, dae_lrs, clf_lrs: (G,) each member's settings.
        variables: the members' variables stacked on a leading axis of G (each member's best
            held-out classifier); :func:`member_variables` takes one out.
        dae_eval: (E1, G) held-out reconstruction MSE after each stage-1 evaluation.
        dae_eval_steps: (E1,) their step numbers.
        clf_eval: (E2, G) held-out top-1 guide accuracy after each stage-2 evaluation.
        clf_eval_family: (E2, G, 4) the same per noise family (:data:`~.data.FAMILIES`).
        clf_eval_steps: (E2,) their step numbers.
        best_accuracy: (G,) the held-out accuracy of the kept classifier.
        seconds: wall time of the whole grid (s).
    """

    seeds: np.ndarray
    dae_lrs: np.ndarray
    clf_lrs: np.ndarray
    variables: dict
    dae_eval: np.ndarray
    dae_eval_steps: np.ndarray
    clf_eval: np.ndarray
    clf_eval_family: np.ndarray
    clf_eval_steps: np.ndarray
    best_accuracy: np.ndarray
    seconds: float

    @property
    def size(self) -> int:
        return int(self.seeds.shape[0])


def grid_members(seeds=(0,), dae_lrs=(1e-3,), clf_lrs=(1e-3,)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Cartesian product of the settings as three (G,) arrays (seeds slowest, clf_lrs fastest)."""
    rows = list(itertools.product(seeds, dae_lrs, clf_lrs))
    if not rows:
        raise ValueError("an empty grid: give at least one seed and one rate of each stage")
    s, d, c = zip(*rows, strict=True)
    return np.asarray(s, np.int64), np.asarray(d, np.float64), np.asarray(c, np.float64)


def member_variables(result: GridResult, g: int) -> dict:
    """Member ``g``'s variables (the layout of :func:`~.train.init_variables`)."""
    if not 0 <= g < result.size:
        raise IndexError(f"member {g} of a grid of {result.size}")
    return jax.tree.map(lambda a: a[g], result.variables)


def _check(seeds, dae_lrs, clf_lrs):
    seeds = np.asarray(seeds)
    dae_lrs, clf_lrs = np.asarray(dae_lrs, np.float64), np.asarray(clf_lrs, np.float64)
    if not (seeds.ndim == dae_lrs.ndim == clf_lrs.ndim == 1 and seeds.size == dae_lrs.size == clf_lrs.size
            and seeds.size > 0):
        raise ValueError("seeds, dae_lrs and clf_lrs must be 1-D of one length G ≥ 1 (grid_members)")
    for name, lr in (("dae_lrs", dae_lrs), ("clf_lrs", clf_lrs)):
        if not np.all(np.isfinite(lr) & (lr > 0)):
            raise ValueError(f"{name} must be positive and finite, got {lr}")
    if not np.issubdtype(seeds.dtype, np.integer):
        raise ValueError(f"seeds must be integers, got {seeds.dtype}")
    return seeds, dae_lrs, clf_lrs


def _select(mask, new, old):
    """Per member: ``new`` where ``mask`` (G,) is set, else ``old`` (pytrees with a leading G axis)."""
    mask = jnp.asarray(mask)
    return jax.tree.map(lambda n, o: jnp.where(mask.reshape((-1,) + (1,) * (n.ndim - 1)), n, o), new, old)


def train_grid(catalog, camera, config: Config, guide_rows, *, seeds, dae_lrs, clf_lrs,
               progress: bool = True) -> GridResult:
    """Train G models (both stages) side by side; settings per member, steps from ``config.training``.

    Args:
        catalog, camera, config, guide_rows: as :func:`~jstarid.algorithms.rpnet.train.train`
            (``config.training`` sets steps, batch size, evaluation and the data seed).
        seeds: (G,) initialisation seed of each member (:func:`grid_members` forms a product).
        dae_lrs: (G,) stage-1 learning rates.
        clf_lrs: (G,) stage-2 learning rates (cosine-decayed when ``Training.clf_lr_decay``).
        progress: tqdm bars with the grid's best held-out figure.

    Returns:
        :class:`GridResult`.

    Raises:
        ValueError: settings of different lengths, non-positive rates or non-integer seeds.
    """
    start = time.perf_counter()
    seeds, dae_lrs, clf_lrs = _check(seeds, dae_lrs, clf_lrs)
    t = config.training
    n_classes = int(len(guide_rows))
    tables = build_tables(catalog, camera, config, guide_rows)
    _, k_eval, k_dae, k_clf = jax.random.split(jax.random.key(t.seed), 4)
    held_out = make_batch(k_eval, catalog, camera, config, tables, t.eval_size)
    next_batch = batch_source(catalog, camera, config, tables, k_dae)
    dae_steps, clf_steps = t.steps(n_classes)
    # each member's initialisation: the k_init that train() derives from its seed
    init_keys = jnp.stack([jax.random.split(jax.random.key(int(s)), 4)[0] for s in seeds])
    variables = jax.vmap(lambda k: init_variables(k, config, n_classes))(init_keys)
    # Adam with the rate in its state (one per member); update() reads the rate from the state. Only
    # the rate is injected: b1, b2, eps stay Python constants, exactly as optax.adam in train()
    adam = optax.inject_hyperparams(optax.adam, static_args=("b1", "b2", "eps", "eps_root", "nesterov"))
    tx = adam(learning_rate=0.0)
    d_lr, c_lr = jnp.asarray(dae_lrs, jnp.float32), jnp.asarray(clf_lrs, jnp.float32)

    # Stage 1: denoising autoencoders (eq. 5), one vmapped step for all members.
    dae_loss = dae_loss_fn(config, n_classes)

    def dae_step(params, state, noisy, clean):
        (_, mse), grads = jax.value_and_grad(dae_loss, has_aux=True)(params, noisy, clean)
        updates, state = tx.update(grads, state, params)
        return optax.apply_updates(params, updates), state, mse

    dae_step = jax.jit(jax.vmap(dae_step, in_axes=(0, 0, None, None)))
    dae_eval = jax.jit(jax.vmap(lambda p, x, y: dae_loss(p, x, y)[1], in_axes=(0, None, None)))
    params = {"generator": variables["generator"], "decoder": variables["decoder"]}
    state = jax.vmap(lambda lr, p: adam(learning_rate=lr).init(p))(d_lr, params)
    dae_hist, dae_at = [], []
    bar = tqdm(range(dae_steps), desc=f"RpNet grid of {seeds.size}, stage 1", disable=not progress)
    for s in bar:
        batch = next_batch(k_dae, s)
        params, state, _ = dae_step(params, state, batch.noisy, batch.clean)
        if (s + 1) % t.eval_every == 0 or s + 1 == dae_steps:
            dae_hist.append(np.asarray(dae_eval(params, held_out.noisy, held_out.clean)))
            dae_at.append(s + 1)
            bar.set_postfix(best_held_out_mse=f"{dae_hist[-1].min():.4f}")
    variables = {**variables, **params}

    # Stage 2: classifiers on the frozen generators' codes (eq. 6); the cosine factor is shared.
    clf_loss = clf_loss_fn(config, n_classes)
    factor = clf_learning_rate(dataclasses.replace(t, clf_lr=1.0), clf_steps)
    factor = factor if callable(factor) else (lambda _, f=factor: f)

    def clf_step(params, stats, state, lr, gen_params, step, noisy, label):
        (_, (ce, stats)), grads = jax.value_and_grad(clf_loss, has_aux=True)(
            params, stats, gen_params, noisy, label)
        state = state._replace(hyperparams={**state.hyperparams, "learning_rate": lr * factor(step)})
        updates, state = tx.update(grads, state, params)
        return optax.apply_updates(params, updates), stats, state, ce

    clf_step = jax.jit(jax.vmap(clf_step, in_axes=(0, 0, 0, 0, 0, None, None, None)))

    def predict(v, x):
        return jnp.argmax(predict_logits(v, x, config=config, n_classes=n_classes), -1)

    predict = jax.jit(jax.vmap(predict, in_axes=(0, None)))
    family = np.asarray(held_out.family)
    label = np.asarray(held_out.label)
    clf = dict(variables["classifier"])
    state = jax.vmap(lambda lr, p: adam(learning_rate=lr).init(p))(c_lr, clf["params"])
    best_acc = np.full(seeds.size, -1.0)
    best = clf
    clf_hist, clf_fam, clf_at = [], [], []
    bar = tqdm(range(clf_steps), desc=f"RpNet grid of {seeds.size}, stage 2", disable=not progress)
    for s in bar:
        batch = next_batch(k_clf, s)
        p, b, state, _ = clf_step(clf["params"], clf["batch_stats"], state, c_lr, variables["generator"],
                                  s, batch.noisy, batch.label)
        clf = {"params": p, "batch_stats": b}
        if (s + 1) % t.eval_every == 0 or s + 1 == clf_steps:
            hit = np.asarray(predict({**variables, "classifier": clf}, held_out.noisy)) == label[None]
            acc = hit.mean(axis=1)
            clf_hist.append(acc)
            clf_fam.append(np.stack([hit[:, family == i].mean(axis=1) for i in range(len(FAMILIES))], -1))
            clf_at.append(s + 1)
            better = (acc > best_acc) | (not t.early_stop)
            best = _select(better, clf, best)
            best_acc = np.where(better, acc, best_acc)
            bar.set_postfix(best_held_out_acc=f"{acc.max():.3f}")
    if clf_steps == 0:
        best = clf
    variables = {**variables, "classifier": best}
    return GridResult(
        seeds=seeds, dae_lrs=dae_lrs, clf_lrs=clf_lrs, variables=variables,
        dae_eval=np.asarray(dae_hist).reshape(-1, seeds.size), dae_eval_steps=np.asarray(dae_at, np.int64),
        clf_eval=np.asarray(clf_hist).reshape(-1, seeds.size),
        clf_eval_family=np.asarray(clf_fam).reshape(-1, seeds.size, len(FAMILIES)),
        clf_eval_steps=np.asarray(clf_at, np.int64), best_accuracy=best_acc,
        seconds=time.perf_counter() - start)
