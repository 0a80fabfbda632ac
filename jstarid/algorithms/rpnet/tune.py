"""Vectorized search of the weight-searching strategy's weights (§II-E, eqs. 9–11, Table 5).

Only the choice of the confident pair depends on the weights po_i, pr_j, so the network runs once:
:func:`pair_tables` stores per scene the top-3 probabilities p_ij, the admissibility of the 27 pairs
and which pair is true; :func:`weight_grid_search` scores every (po, pr) of a grid in one ``vmap``.
Figure of merit: the chosen pair (highest eq. 11 score among the admissible) names both detections
correctly, which is what the naming step needs.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.rpnet.config import Config
from jstarid.algorithms.rpnet.identify import PAIRS, network_candidates, pair_checks, weight_search
from jstarid.runtime.program_store import stored_jit

__all__ = ["mixed_noise", "pair_tables", "simplex_grid", "weight_grid_search"]


def mixed_noise(n: int):
    """The tuning scripts' test set: n scenes' noise, one quarter per family of the paper's Figs. 8–11
    (scene i: family i mod 4, level j = i // 4): position σ 0.2–1.6 px (step 0.2), magnitude
    σ ∈ {0.323, …, 0.969}, 1–5 missing stars, false-star ratio 5–50 % (false V 0–6).

    Returns:
        ``(noise, family)``: a :class:`jstarid.NoiseConfig` of (n,) fields and the (n,) int family.
    """
    from jstarid.simulator import NoiseConfig

    i = np.arange(n)
    fam, j = i % 4, i // 4
    pos = np.where(fam == 0, 0.2 * (1 + j % 8), 0.0)
    mag = np.where(fam == 1, np.array([0.323, 0.484, 0.646, 0.807, 0.969])[j % 5], 0.0)
    miss = np.where(fam == 2, 1 + j % 5, 0)
    ratio = np.where(fam == 3, 0.05 * (1 + j % 10), 0.0)
    noise = NoiseConfig(position_sigma_px=pos.astype(np.float32), magnitude_sigma=mag.astype(np.float32),
                        n_missing=miss.astype(np.int32), false_ratio=ratio.astype(np.float32),
                        false_mag_min=0.0, false_mag_max=6.0)
    return noise, fam


def simplex_grid(step: float = 0.05, *, decreasing: bool = True) -> np.ndarray:
    """Weight triples on the simplex w1 + w2 + w3 = 1 (eq. 9), w ≥ 0, in steps of ``step``.

    Args:
        step: grid spacing (1/step must be an integer).
        decreasing: keep only w1 ≥ w2 ≥ w3 (nearest detection / most probable candidate first, as
            the paper assigns them).

    Returns:
        (G, 3) float32 weights.
    """
    n = round(1.0 / step)
    if abs(n * step - 1.0) > 1e-9:
        raise ValueError(f"1/step must be an integer, got step={step}")
    out = [(a, b, n - a - b) for a, b in itertools.product(range(n + 1), repeat=2) if a + b <= n]
    if decreasing:
        out = [w for w in out if w[0] >= w[1] >= w[2]]
    return (np.asarray(out, np.float64) / n).astype(np.float32)


def pair_tables(database, scenes, config: Config | None = None) -> dict[str, np.ndarray]:
    """Run the network once and tabulate what the weight search needs, per scene.

    Args:
        database: :class:`~jstarid.algorithms.rpnet.database.Database`.
        scenes: (B, N) :class:`~jstarid.scene.Scene` (with ``truth``).
        config: identification settings (pair checks); ``None`` uses ``database.config``.

    Returns:
        dict of NumPy arrays: ``probs`` (B, 3, 3) float32 p_ij; ``pair_ok`` (B, 27) bool admissible
        pairs (:data:`~jstarid.algorithms.rpnet.identify.PAIRS` order); ``pair_correct`` (B, 27) bool
        both candidates are the true stars of their detections; ``guide_correct`` (B, 3) bool the top
        candidate of S_i is its true star.
    """
    config = database.config if config is None else config
    camera = database.camera
    guide_rows = jnp.asarray(database.guide_rows, jnp.int32)
    out = {k: [] for k in ("probs", "pair_ok", "pair_correct", "guide_correct")}
    chunk = max(1, config.batch_chunk)
    for start in range(0, scenes.batch_size, chunk):
        part = scenes[start:start + chunk]
        near, probs, cls = network_candidates(part.xy, part.valid, database.inference_weights, camera=camera,
                                              config=config, n_classes=database.n_classes, mag=part.mag)
        ok, correct, top = _tables_chunk(part.xy, part.valid, part.truth, near, cls, guide_rows,
                                         database.star_vectors, config.tuning().pair_tol_px,
                                         camera=camera)
        for name, value in (("probs", probs), ("pair_ok", ok), ("pair_correct", correct),
                            ("guide_correct", top)):
            out[name].append(np.asarray(value))
    return {k: np.concatenate(v) for k, v in out.items()}


@functools.partial(stored_jit, static_argnames=("camera",))
def _tables_chunk(xy, valid, truth, near, cls, guide_rows, star_vectors, pair_tol_px, *, camera):
    def one(xy_s, valid_s, truth_s, near_s, cls_s):
        body = camera.unproject(xy_s)
        cand_rows = guide_rows[cls_s]  # (3, 3)
        ok = pair_checks(body, valid_s, near_s, cand_rows, star_vectors, pair_tol_px, camera=camera)
        hit = (cand_rows == truth_s[near_s][:, None]) & valid_s[near_s][:, None]  # (3, 3)
        i, j, k, m = (jnp.asarray(PAIRS[:, c]) for c in range(4))
        return ok, hit[i, j] & hit[k, m], hit[:, 0]

    return jax.vmap(one)(xy, valid, truth, near, cls)


@stored_jit
def _grid(probs, pair_ok, pair_correct, po, pr):
    def one_setting(po_w, pr_w):
        best, _, found = jax.vmap(lambda p, ok: weight_search(p, ok, po_w, pr_w))(probs, pair_ok)
        right = found & jnp.take_along_axis(pair_correct, best[:, None], axis=1)[:, 0]
        return jnp.mean(right), jnp.mean(found & ~right), jnp.mean(~found)

    over_pr = jax.vmap(one_setting, in_axes=(None, 0))
    return jax.vmap(over_pr, in_axes=(0, None))(po, pr)


def weight_grid_search(probs, pair_ok, pair_correct, position_weights, probability_weights) -> dict:
    """Eq. 11 pair choice for every (po, pr) combination of two weight lists, in one batched call.

    Args:
        probs: (B, 3, 3) p_ij per scene.
        pair_ok: (B, 27) bool admissible pairs.
        pair_correct: (B, 27) bool pair names both detections correctly.
        position_weights: (P, 3) po triples.
        probability_weights: (Q, 3) pr triples.

    Returns:
        dict with (P, Q) float arrays ``correct`` (rate of scenes whose chosen pair is correct),
        ``wrong`` (a wrong pair chosen) and ``none`` (no admissible pair), and ``best``: the
        ``(po, pr)`` of the highest ``correct`` (first in grid order on ties) with its rates.
    """
    po = jnp.asarray(position_weights, jnp.float32).reshape(-1, 3)
    pr = jnp.asarray(probability_weights, jnp.float32).reshape(-1, 3)
    correct, wrong, none = (np.asarray(a) for a in _grid(jnp.asarray(probs, jnp.float32),
                                                         jnp.asarray(pair_ok, bool),
                                                         jnp.asarray(pair_correct, bool), po, pr))
    a, b = np.unravel_index(int(np.argmax(correct)), correct.shape)
    best = {"position_weights": np.asarray(po[a]).tolist(), "probability_weights": np.asarray(pr[b]).tolist(),
            "correct": float(correct[a, b]), "wrong": float(wrong[a, b]), "none": float(none[a, b])}
    return {"correct": correct, "wrong": wrong, "none": none, "best": best}
