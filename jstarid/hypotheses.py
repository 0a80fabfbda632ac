"""Hypothesize and verify: a scene that an algorithm left unsolved, solved from any three of its
detections that are stars — however many false detections surround them.

Every algorithm picks its pattern from the brightest detections. Among false detections as bright
as the stars (hot pixels, cosmic rays, satellites) those are mostly false, and the algorithm fails
cleanly where the frame still holds five or six stars. This stage, the finishing stage's first step
(``Finishing.hypotheses``), looks at every triangle instead (as openstartracker's BEAST and
astrometry.net do with their own keys):

1. the ``n`` brightest valid detections (``Finishing.hypotheses``) → camera-frame unit vectors; every
   triple i < j < k of them. A scene with more detections that this leaves unsolved is searched
   again over its ``Finishing.crowded_hypotheses`` brightest (a second pass: among 80 false
   detections as bright as the stars, the 48 brightest rarely hold five stars);
2. per triple, the catalog triangles whose sorted sides are within ε of the triple's
   (:mod:`jstarid.triangle_index`, two binary searches) and that turn the same way (the sign of the
   triple product, which a rotation keeps); vertices correspond by the side opposite them. Each
   (triple, triangle) is a hypothesis; the first ``capacity`` of a scene are kept (more is flagged);
3. each hypothesis's attitude (TRIAD on two of its stars) points every detection at the sky; a
   detection within ε of a catalog star confirms it (:func:`jstarid.completion.name_stars`: the
   nearest star, no second one within ε, no star claimed twice). The triangle's third star must be
   confirmed too.
   The hypothesis with the most confirmations wins; another one with as many that names the
   detections otherwise makes the scene ambiguous (failed);
4. the attitude is refitted to the winner's names (Wahba), every detection is named from it, and the
   scene is claimed only when it names at least ``3 + min_confirm`` stars and their false-match
   probability (:mod:`jstarid.false_match`: could a wrong attitude have confirmed as many?) is at most
   ``Finishing.hypothesis_false_match``. The search tries a few thousand triangles per scene, and the
   probability's union bound counts every pair hypothesis a blind search could try, so the threshold
   holds for this search too.

``search_scene`` is the per-scene jit-able kernel (batched with ``lax.map``); :func:`solve_unsolved`
is the host entry the finishing stage calls.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.attitude import solve_wahba, triad
from jstarid.completion import first_argmax, name_stars
from jstarid.false_match import false_match_probability
from jstarid.geometry.angles import pairwise_angles, turn_sign
from jstarid.runtime import pad_rows, padded_indices
from jstarid.runtime.pairs import skip_padding
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Identification, Scene
from jstarid.sky_index import build_sky_index, local_stars
from jstarid.triangle_index import TriangleIndex, build_triangle_index, query, stars_that_fit

__all__ = ["SearchOutcome", "Searched", "all_triples", "search_scene", "solve_unsolved"]

TRIPLE_CHUNK = 512  # triples vmapped together inside a scene's lax.map
HYPOTHESIS_CHUNK = 128  # hypotheses verified together
SCENE_CHUNK = 64  # scenes per compiled call
# The second pass verifies this many times the first's hypotheses (65,536 of 4,096): a deep
# catalog (the 6° camera at V 7.2) matches many triangles per triple, and four times left crowded
# frames of a dozen stars unsolved (experiments/probes/second_pass.py, docs/design/hypotheses.md).
SECOND_PASS_CAPACITY = 16
# A deep catalog is searched over its brightest star per sky cell only where a frame holds at most
# this many catalog stars on average: a sparse field, whose few stars a brightest-detections pattern
# loses among clutter (a 6° field at V 7.2: 13). Denser fields (the papers' cameras: 25–50) hold
# patterns enough for the algorithms' own steps, and keep their results and cost without the search.
SPARSE_STARS_PER_FRAME = 20.0
SKY_DEG2 = 4 * math.pi * (180 / math.pi) ** 2  # the whole sky (deg²)


class Searched(NamedTuple):
    """What :func:`search_scene` returns for one scene (a leading batch axis when batched).

    Attributes:
        ids: (cap,) int32 catalog rows named from the winning attitude (−1 none).
        ok: () bool, a winner with at least ``3 + min_confirm`` names and no rival.
        attitude: (3, 3) float32 C of the names (NaN when not ``ok``).
        confirmed: () int32 the winner's confirmed detections (its triangle included).
        n_hypotheses: () int32 (triple, triangle) hypotheses found (may exceed the capacity).
        overflow: () bool, more hypotheses than the capacity (the rest were not verified) or a
            triple with more matching triangles than its share.
    """

    ids: jax.Array
    ok: jax.Array
    attitude: jax.Array
    confirmed: jax.Array
    n_hypotheses: jax.Array
    overflow: jax.Array


def all_triples(n: int) -> np.ndarray:
    """(C(n, 3), 3) int32 every triple i < j < k of n detections, lexicographic (brightest first)."""
    if n < 3:
        return np.zeros((1, 3), np.int32)
    return np.asarray(list(itertools.combinations(range(n), 3)), np.int32)


def search_scene(xy, valid, mag, triples, *, index: TriangleIndex, star_vectors, cells, grid: int, camera,
                 n_use: int, eps_rad: float, min_confirm: int, capacity: int, per_triple: int) -> Searched:
    """Steps 1–4 (but the false-match test) on one scene (module docstring).

    Args:
        xy: (cap, 2) float32 centroids (px). valid: (cap,) bool. mag: (cap,) float32 (mag).
        triples: (T, 3) int32 :func:`all_triples` of ``min(n_use, cap)``, padded with copies of the
            first to a multiple of :data:`TRIPLE_CHUNK` (an argument, not a constant: XLA takes
            minutes over a loop that slices a constant).
        index: the catalog's :class:`~jstarid.triangle_index.TriangleIndex`.
        star_vectors: (M, 3) float32 ICRS unit vectors of the catalog rows.
        cells: (6·G·G, K) int32 sky-index lists over ``star_vectors``; grid: G.
        camera: the :class:`~jstarid.camera.Camera` (pinhole).
        n_use: the brightest detections the triples come from. eps_rad: side and confirmation
            tolerance (rad). min_confirm: confirmations needed beyond the triangle.
        capacity: hypotheses verified per scene. per_triple: matching triangles kept per triple.
    """
    cap = xy.shape[0]
    n = min(n_use, cap)
    _, sel = jax.lax.top_k(-jnp.where(valid, mag, jnp.inf), n)
    use = valid[sel]
    body = camera.unproject(xy[sel])
    theta = pairwise_angles(body)

    def one_triple(t):
        opposite = jnp.stack([theta[t[1], t[2]], theta[t[0], t[2]], theta[t[0], t[1]]])
        order = jnp.argsort(opposite)
        verts = t[order]  # vertex m is opposite the m-th shortest side, as in the index
        slots, match = query(index, opposite[order], eps_rad)
        abc = index.stars[slots]
        va, vb, vc = (star_vectors[abc[:, m]] for m in range(3))
        turn = turn_sign(body[verts[0]], body[verts[1]], body[verts[2]])
        match = match & (turn_sign(va, vb, vc) == turn) & jnp.all(use[verts])
        count = jnp.sum(match).astype(jnp.int32)
        (first,) = jnp.nonzero(match, size=per_triple, fill_value=0)
        return verts, abc[first], jnp.arange(per_triple) < count, count

    n_t = math.comb(n, 3)
    padded = triples.shape[0]
    chunk = min(TRIPLE_CHUNK, padded)
    verts, abc, has, counts = jax.lax.map(jax.vmap(one_triple), triples.reshape(-1, chunk, 3))
    real = (jnp.arange(padded) < n_t)
    verts, abc = verts.reshape(padded, 3), abc.reshape(padded, per_triple, 3)
    has = has.reshape(padded, per_triple) & real[:, None]
    counts = jnp.where(real, counts.reshape(padded), 0)
    total = jnp.sum(counts)
    (flat,) = jnp.nonzero(has.reshape(-1), size=capacity, fill_value=0)
    live = jnp.arange(capacity) < jnp.sum(has)
    h_verts = verts[flat // per_triple]  # (H, 3)
    h_abc = abc.reshape(-1, 3)[flat]  # (H, 3)

    def verify(hyp):
        v, s, alive = hyp
        att = triad(body[v[0]], body[v[1]], star_vectors[s[0]], star_vectors[s[1]])
        rows, vecs, _ = local_stars(cells, star_vectors, att[2], grid)
        local, hit = name_stars(att, body, use, vecs, eps_rad)
        named = rows[local]
        own = jnp.all(hit[v] & (named[v] == s))
        return att, jnp.where(alive & own, jnp.sum(hit), 0).astype(jnp.int32), jnp.where(hit, named, -1)

    atts, scores, names = _verify_live(verify, (h_verts, h_abc, live), jnp.minimum(jnp.sum(has), capacity), n)
    win = first_argmax(scores)
    best = scores[win]
    # a rival names the detections otherwise (the same stars found from another triple agree, though
    # their TRIAD attitudes differ by the noise of their short baselines)
    differs = jnp.any(names != names[win][None, :], axis=1)
    rival = jnp.any(differs & (scores == best))
    # refit to the winner's names, then name every detection of the scene from that attitude
    chosen = names[win]
    att = solve_wahba(body, star_vectors[jnp.maximum(chosen, 0)], (chosen >= 0).astype(jnp.float32))
    every = camera.unproject(xy)
    rows, vecs, _ = local_stars(cells, star_vectors, att[2], grid)
    local, named = name_stars(att, every, valid, vecs, eps_rad)
    ids = jnp.where(named, rows[local], -1)
    ok = (best >= 3 + min_confirm) & ~rival & (jnp.sum(named) >= 3 + min_confirm)
    att = solve_wahba(every, star_vectors[jnp.maximum(ids, 0)], named.astype(jnp.float32))
    return Searched(ids=jnp.where(ok, ids, -1), ok=ok, attitude=jnp.where(ok, att, jnp.nan),
                    confirmed=best, n_hypotheses=total,
                    overflow=(jnp.sum(has) > capacity) | jnp.any(counts > per_triple))


def _verify_live(verify, hyps, n_live, n: int):
    """``jax.lax.map(verify, hyps)`` over the first ``n_live`` hypotheses only, in chunks of
    :data:`HYPOTHESIS_CHUNK` (a ``while_loop``: a scene with a few dozen hypotheses does not pay for
    the whole capacity). The rest keep score 0, no names and a zero attitude: the winner and the rival
    test read only scores above 0 (a scene whose best score is 0 is not ``ok``).

    Args:
        verify: one hypothesis → ``(attitude (3, 3), score (), names (n,))``.
        hyps: pytree of (H, ...) hypotheses. n_live: () int32 ≤ H. n: static detections searched.
    """
    h = jax.tree.leaves(hyps)[0].shape[0]
    chunk = min(HYPOTHESIS_CHUNK, h)
    padded = -(-h // chunk) * chunk
    hyps = pad_rows(hyps, padded)  # zeros, not live
    out = (jnp.zeros((padded, 3, 3), jnp.float32), jnp.zeros(padded, jnp.int32),
           jnp.full((padded, n), -1, jnp.int32))

    def body(state):
        i, acc = state
        part = jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, i * chunk, chunk), hyps)
        done = jax.vmap(verify)(part)
        return i + 1, tuple(jax.lax.dynamic_update_slice_in_dim(a, d.astype(a.dtype), i * chunk, 0)
                            for a, d in zip(acc, done, strict=True))

    _, out = jax.lax.while_loop(lambda state: state[0] * chunk < n_live, body, (jnp.int32(0), out))
    return tuple(a[:h] for a in out)


@functools.partial(stored_jit, static_argnames=("grid", "camera", "n_use", "eps_rad", "min_confirm",
                                                "capacity", "per_triple"))
def _search_chunk(xy, valid, mag, real, triples, index, star_vectors, cells, **static):
    """:func:`search_scene` on each scene of a padded chunk, one after another; the padding rows
    (``real`` False) are skipped (:func:`~jstarid.runtime.pairs.skip_padding`), so a call of 16 for 3
    scenes costs 3 searches."""
    fn = functools.partial(search_scene, triples=triples, index=index, star_vectors=star_vectors, cells=cells,
                           **static)

    out = jax.eval_shape(fn, xy[0], valid[0], mag[0])
    skipped = Searched(ids=jnp.full(out.ids.shape, -1, out.ids.dtype), ok=jnp.zeros((), bool),
                       attitude=jnp.full(out.attitude.shape, jnp.nan, out.attitude.dtype),
                       confirmed=jnp.zeros((), out.confirmed.dtype),
                       n_hypotheses=jnp.zeros((), out.n_hypotheses.dtype), overflow=jnp.zeros((), bool))
    return skip_padding(fn, real, (xy, valid, mag), skipped)


def padded_triples(n: int) -> np.ndarray:
    """:func:`all_triples` of n, padded with copies of the first to a whole number of chunks."""
    triples = all_triples(n)
    chunk = min(TRIPLE_CHUNK, len(triples))
    extra = -len(triples) % chunk
    return np.concatenate([triples, np.repeat(triples[:1], extra, 0)])


def _search_index(vectors: np.ndarray, star_mags, camera, eps_rad: float) -> TriangleIndex:
    """The triangle index of the search: of every row, or (a sparse field's deep catalog, ``star_mags``
    given) of the rows :func:`~jstarid.triangle_index.stars_that_fit` keeps, its stars numbered as
    rows of ``vectors`` (which verification names from)."""
    per_frame = vectors.shape[0] * camera.fov_x_deg * camera.fov_y_deg / SKY_DEG2
    if star_mags is None or per_frame > SPARSE_STARS_PER_FRAME:
        return build_triangle_index(vectors, camera, eps_rad)
    kept = stars_that_fit(vectors, star_mags, camera)
    index = build_triangle_index(vectors[kept], camera, eps_rad)
    if kept.size == vectors.shape[0]:
        return index
    whole = hashlib.sha1(np.ascontiguousarray(vectors).tobytes()).hexdigest()[:16]
    return dataclasses.replace(index, stars=jnp.asarray(kept)[index.stars], key=f"{index.key}-in-{whole}")


def _sky_cells(star_vectors: np.ndarray, index: TriangleIndex, camera, eps_rad: float):
    """The sky index of the catalog for the camera (memoised by :func:`build_sky_index`): the stars any
    boresight can see, out to 4 ε past the field (a TRIAD attitude's error)."""
    sky = build_sky_index(np.asarray(star_vectors, np.float64), camera.half_diagonal_rad,
                          margin_rad=4 * eps_rad, key=f"{index.key}-hypotheses")
    return sky.device_arrays()[0], sky.grid


class SearchOutcome(NamedTuple):
    """What :func:`solve_unsolved` returns.

    Attributes:
        result: the given :class:`~jstarid.scene.Identification` with the scenes the search solved
            filled in (ids, ok, attitude; their focal scale and k1 NaN until the camera check fits them).
        solved: (B,) bool NumPy, those scenes.
        overflow: (B,) bool NumPy, searched scenes with more hypotheses than the capacity, or a triple
            with more matching catalog triangles than ``per_triple``: the rest were not verified (a
            claim still needs the false-match test; a failure may be the search's, not the scene's).
    """

    result: Identification
    solved: np.ndarray
    overflow: np.ndarray


def solve_unsolved(result: Identification, scenes: Scene, *, star_vectors, camera, n_use: int,
                   eps_px: float, min_confirm: int, max_false_match: float, capacity: int = 4096,
                   per_triple: int = 16, star_mags=None, n_crowded: int = 0,
                   rows: np.ndarray | None = None) -> SearchOutcome:
    """The search on every scene ``result`` leaves unsolved; claims pass the false-match test.

    Args:
        result: an algorithm's (B, N) :class:`~jstarid.scene.Identification` of ``scenes``.
        scenes: (B, N) :class:`~jstarid.scene.Scene` from ``camera`` (pinhole centroids, px).
        star_vectors: (M, 3) ICRS unit vectors of the catalog rows ``result.ids`` names.
        camera: the :class:`~jstarid.camera.Camera`.
        n_use: the brightest detections whose triples are tried (≥ 4).
        eps_px: side and confirmation tolerance (px at the focal length).
        min_confirm: confirmed detections needed beyond the triangle (≥ 1).
        max_false_match: the largest false-match probability a claim may have.
        capacity: hypotheses verified per scene. per_triple: matching triangles kept per triple.
            (4,096 and 16: no scene of 128 with 40 false detections on ``challenge10`` overflowed;
            2,048 and 4 left 23 unfinished, and verifying costs ≈ 25 % more at 4,096.)
        star_mags: (M,) V of the rows (mag). Given, a catalog with too many triangles per frame of
            a sparse field (at most :data:`SPARSE_STARS_PER_FRAME` stars a frame: a deep catalog on
            a narrow camera) is searched over the triangles of its brightest star per sky cell
            (:func:`jstarid.triangle_index.stars_that_fit`), still verified against every row.
        n_crowded: a scene with more than ``n_use`` valid detections that the first pass leaves
            unsolved is searched again over its ``n_crowded`` brightest (a crowded frame, whose
            stars the brightest ``n_use`` leave out); 0 (or ≤ ``n_use``): no such pass. A scene the
            first pass leaves unsolved with hypotheses past ``capacity`` is searched again over the
            same detections. Either second pass verifies :data:`SECOND_PASS_CAPACITY` times
            ``capacity`` hypotheses.
        rows: the unsolved scenes to search ((R,) int indices; default: every one). A caller that
            pads a sub-batch with copies of a scene names the real rows, so the copies are not
            searched again.

    Returns:
        :class:`SearchOutcome`.

    Raises:
        jstarid.triangle_index.TooManyTriangles: the catalog (or, with ``star_mags``, its chosen
            stars) has too many triangles per frame.
    """
    ok = np.asarray(result.ok)
    b = ok.shape[0]
    if rows is None:
        rows = np.flatnonzero(~ok)
    else:
        rows = np.asarray(rows, np.intp)
        rows = rows[~ok[rows]]
    solved, overflow = np.zeros(b, bool), np.zeros(b, bool)
    eps_rad = float(eps_px) / camera.f_px
    vectors = np.asarray(star_vectors, np.float32)
    index = _search_index(vectors, star_mags, camera, eps_rad) if rows.size else None
    if index is None or index.size == 0:  # nothing to search, or no three stars fit in a frame
        return SearchOutcome(result, solved, overflow)
    cells, grid = _sky_cells(vectors, index, camera, eps_rad)
    xy, valid, mag = (np.asarray(a) for a in (scenes.xy, scenes.valid, scenes.mag))
    search = functools.partial(_search_rows, xy=xy, valid=valid, mag=mag, index=index,
                               vectors=jnp.asarray(vectors), cells=cells, grid=grid, camera=camera,
                               eps_rad=eps_rad, min_confirm=int(min_confirm), per_triple=int(per_triple))

    def claims(found: Searched, searched_rows: np.ndarray) -> np.ndarray:
        candidate = Identification(ids=jnp.asarray(found.ids), ok=jnp.asarray(found.ok),
                                   attitude=jnp.asarray(found.attitude))
        p = false_match_probability(scenes[searched_rows], candidate, vectors, camera)
        return found.ok & (p <= max_false_match)

    found = search(rows, n_use=int(n_use), capacity=int(capacity))
    won = claims(found, rows)
    # the second pass, where the first found no claim: a crowded scene over more detections, a scene
    # that overflowed over the hypotheses past the capacity
    crowded = ~won & (valid[rows].sum(axis=1) > n_use) & (n_crowded > n_use)
    unfinished = ~won & (found.n_hypotheses > capacity) & ~crowded
    for again, n_again in ((crowded, int(n_crowded)), (unfinished, int(n_use))):
        if again.any():
            more = search(rows[again], n_use=n_again, capacity=SECOND_PASS_CAPACITY * int(capacity))
            won[again] = claims(more, rows[again])
            for field, wider in zip(found, more, strict=True):
                field[again] = wider
    overflow[rows] = found.overflow
    take = rows[won]
    solved[take] = True
    if not take.size:
        return SearchOutcome(result, solved, overflow)

    n_won = int(won.sum())
    unfitted = np.full(n_won, np.nan, np.float32)  # the camera check fits them next
    found_part = Identification(
        ids=found.ids[won], ok=found.ok[won], attitude=found.attitude[won].astype(np.float32),
        focal_scale=None if result.focal_scale is None else unfitted,
        distortion_k1=None if result.distortion_k1 is None else unfitted)
    filled_result = result.with_rows(take, found_part)
    return SearchOutcome(filled_result, solved, overflow)


def _search_rows(rows: np.ndarray, *, xy, valid, mag, index, vectors, cells, grid: int, camera, n_use: int,
                 eps_rad: float, min_confirm: int, capacity: int, per_triple: int) -> Searched:
    """:func:`search_scene` on the scenes ``rows`` of the host arrays, :data:`SCENE_CHUNK` at a time;
    NumPy :class:`Searched` of ``len(rows)`` scenes."""
    static = dict(grid=grid, camera=camera, n_use=n_use, eps_rad=eps_rad, min_confirm=min_confirm,
                  capacity=capacity, per_triple=per_triple)
    triples = jnp.asarray(padded_triples(min(n_use, xy.shape[1])))
    found = []
    for lo in range(0, rows.size, SCENE_CHUNK):
        # sizes 16, 32, 64 only: each is one compiled program (≈ 5 s at 48 detections)
        part = padded_indices(rows[lo:lo + SCENE_CHUNK], floor=16)
        n = min(SCENE_CHUNK, rows.size - lo)
        out = _search_chunk(jnp.asarray(xy[part], jnp.float32), jnp.asarray(valid[part]),
                            jnp.asarray(mag[part], jnp.float32), jnp.arange(part.size) < n, triples, index,
                            vectors, cells, **static)
        found.append([np.asarray(a)[:n] for a in out])
    return Searched(*(np.concatenate(parts) for parts in zip(*found, strict=True)))
