"""Names from a match: what a pass of :func:`~jstarid.algorithms.sgm.identify` does after the search.

Algorithm 1 ends with J*, its vertex correspondence and δ (:class:`~.search.SearchOutcome`). Every
detection of G_I, the main star included, is named through that correspondence, never through the
candidate's main-star label (≈ 7 % of main stars have a twin graph, conventions §7 pitfall 2);
detections outside the circle and unmatched vertices get −1 (:func:`names_from_match`).

Not in the paper (:class:`~.config.Config`), in the order they run:

- ``vertex_check_deg`` (off): unnames vertices whose edges disagree with the database graph
  (:func:`check_vertices`);
- ``leftover_tol_deg`` (on): names the members of G_I the match left unnamed from the attitude of
  the matched stars (:func:`name_leftovers`);
- ``verify`` (on, :mod:`.verify`): fails a scene rather than mis-identify it
  (:func:`verify_claims`);
- ``verify.rename``: names what the verification left unnamed and verifies again
  (:func:`rename_and_reverify`);
- ``verify.retries``: strikes out a rejected match and takes the search's next answer
  (:func:`names_with_retries`; :mod:`.search`, "Resumption"), so the verification joins
  Algorithm 1's acceptance test.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.sgm.config import Config
from jstarid.algorithms.sgm.graph import ImageGraph
from jstarid.algorithms.sgm.search import SearchOutcome
from jstarid.algorithms.sgm.subgraph import Ranking
from jstarid.algorithms.sgm.verify import verify_ids
from jstarid.attitude import estimate_attitude
from jstarid.runtime import map_batch, on_every_device, padded_indices
from jstarid.runtime.padding import MIN_CALL_SIZE
from jstarid.scene import Identification, Scene
from jstarid.sky_index import build_sky_index

__all__ = ["attitude_from_names", "check_vertices", "name_leftovers", "names_from_match",
           "names_from_ranking", "names_with_retries", "rename_and_reverify", "verify_claims",
           "verify_inputs"]


def names_with_retries(db, scenes: Scene, g: ImageGraph, res: SearchOutcome, config: Config,
                       next_outcome: Callable[[SearchOutcome, np.ndarray], SearchOutcome]):
    """:func:`names_from_match`, then, for the matches the verification rejected (``verify.retries``
    times at most), the search's next answer: ``next_outcome(res, redo)`` → the
    :class:`~.search.SearchOutcome` with the scenes ``redo`` (R,) moved on. Not when only the main
    star's name was contested: another graph cannot settle that.

    Returns:
        ``(result, res, contested_main)``: the :class:`~jstarid.scene.Identification`, the last
        outcome and (B,) bool, failed only because the main star's name is contested.
    """
    result, contested = names_from_match(db, scenes, g, res, config)
    contested = contested.copy()  # a view of a device array is read-only
    if not config.verify.on:
        return result, res, contested
    for _ in range(config.verify.retries):
        retry = res.ok & ~np.asarray(result.ok) & ~contested
        if not np.any(retry):
            break
        redo = np.nonzero(retry)[0]
        res = next_outcome(res, redo)
        sub, sub_contested = names_from_match(db, scenes, g, res, config, rows=redo)
        result = _merge(result, sub, redo)
        contested[redo] = sub_contested
    return result, res, contested


def names_from_ranking(db, scenes: Scene, g: ImageGraph, ranking: Ranking,
                       config: Config) -> tuple[Identification, SearchOutcome]:
    """Name and verify each scene's best accepted candidate of a subgraph search's ranking; a
    rejected one gives way to the next in the ranking (:func:`names_with_retries`). Returns
    ``(result, outcome)``."""
    b = ranking.ok.shape[0]
    pick = np.zeros(b, np.int64)
    n_rejected = np.zeros(b, np.int32)

    def next_in_ranking(res, redo):
        pick[redo] += 1
        n_rejected[redo] += 1
        return ranking.outcome_at(pick, n_rejected)

    result, res, _ = names_with_retries(db, scenes, g, ranking.outcome_at(pick, n_rejected), config,
                                        next_in_ranking)
    return result, res


def names_from_match(db, scenes: Scene, g: ImageGraph, res: SearchOutcome, config: Config,
                     rows: np.ndarray | None = None) -> tuple[Identification, np.ndarray]:
    """Every step after the search: names from the correspondence, vertex check, leftover naming,
    verification and renaming (``Config``).

    Args:
        db: :class:`~.database.Database`. scenes: (B, N) :class:`~jstarid.scene.Scene`.
        g: their NumPy :class:`~.graph.ImageGraph` (B, K, …). res: the search's
            :class:`~.search.SearchOutcome`. config: :class:`Config`.
        rows: optional (R,) scene rows to process (the result then has R rows), padded to a coarse
            size of at least :data:`~jstarid.runtime.padding.MIN_CALL_SIZE`
            (:func:`~jstarid.runtime.padded_indices` with ``coarse``), so that the compiled naming and
            verification serve every retry with a few shapes.

    Returns:
        ``(result, main_ambiguous)``: :class:`~jstarid.scene.Identification` and (B,) bool, the scenes
        failed only because their main star's name is contested (:func:`.verify.verify_ids`).
    """
    if rows is not None:
        padded = padded_indices(rows, floor=MIN_CALL_SIZE, coarse=True)
        sub, amb = names_from_match(db, scenes[padded], jax.tree.map(lambda v: v[padded], g),
                                    jax.tree.map(lambda v: v[padded], res), config)
        return sub[:rows.size], amb[:rows.size]
    if config.vertex_check_deg is not None:
        match, ok = check_vertices(g.adj, db.adj, res, config)
        res = res._replace(match=match, ok=ok)
    b, n_det = scenes.valid.shape
    ids = np.full((b, n_det), -1, np.int32)
    sc, vert = np.nonzero(res.match >= 0)
    det = g.members[sc, vert]
    ids[sc, det] = db.members[res.best[sc], res.match[sc, vert]]
    ok = res.ok
    result = Identification(ids=jnp.asarray(ids), ok=jnp.asarray(ok), attitude=None)
    if config.leftover_tol_deg is not None and np.any(ok):
        ids = name_leftovers(db, scenes, result, g, config)
        result = Identification(ids=jnp.asarray(ids), ok=result.ok, attitude=None)
    main_ambiguous = np.zeros(b, bool)
    if config.verify.on and np.any(ok):
        result, main_ambiguous = verify_claims(db, scenes, result, g.main, config)
        if config.verify.rename and config.leftover_tol_deg is not None and np.any(result.ok):
            result = rename_and_reverify(db, scenes, result, g, config)
    return result, main_ambiguous


def _merge(result: Identification, sub: Identification, rows: np.ndarray) -> Identification:
    """``result`` with the scenes ``rows`` replaced by ``sub``'s (R rows, in that order)."""
    ids, ok = np.array(result.ids), np.array(result.ok)  # on the host: no program per row count
    ids[rows], ok[rows] = np.asarray(sub.ids), np.asarray(sub.ok)
    return Identification(ids=jax.device_put(ids), ok=jax.device_put(ok), attitude=None)


def verify_claims(db, scenes: Scene, result: Identification, main, config: Config):
    """:func:`.verify.verify_ids` with the settings of ``config`` → ``(Identification,
    main_ambiguous)``, the latter (B,) NumPy bool.

    Only the scenes ``result`` claims are verified (padded to a coarse size of at least
    :data:`~jstarid.runtime.padding.MIN_CALL_SIZE`, so that a few compiled shapes serve every call:
    each of 1, 2, 4 and 8 claims compiled the verification again in a fresh batch): the
    verification fails every other scene, with no names, anyway.
    """
    ok = np.asarray(result.ok)
    b, n_det = scenes.valid.shape
    ids = np.full((b, n_det), -1, np.int32)
    verified, main_ambiguous = np.zeros(b, bool), np.zeros(b, bool)
    rows = np.flatnonzero(ok)
    if rows.size:
        padded = padded_indices(rows, floor=MIN_CALL_SIZE, coarse=True)
        tables, settings = verify_inputs(db, config)
        named = np.asarray(result.ids)[padded]
        # identify names only the neighbor graph's members (at most its capacity K): the ambiguity
        # tests then run on K rows, not on every detection slot; more names (a caller's own) → all
        n_named = int(np.max(np.sum(named >= 0, axis=1), initial=0))
        max_named = int(db.capacity) if n_named <= db.capacity else None
        sub = scenes[padded]
        out = map_batch(
            _verify_scenes, (sub.xy, sub.mag, sub.valid, jnp.asarray(named), jnp.asarray(ok[padded]),
                             jnp.asarray(np.asarray(main)[padded])),
            tables, static={**settings, "max_named": max_named})
        sub_ids, sub_ok, sub_amb = (np.asarray(x)[:rows.size] for x in out)
        ids[rows], verified[rows], main_ambiguous[rows] = sub_ids, sub_ok, sub_amb
    return Identification(ids=jnp.asarray(ids), ok=jnp.asarray(verified), attitude=None), main_ambiguous


def verify_inputs(db, config: Config):
    """``(tables, settings)`` of :func:`.verify.verify_ids` (``max_named`` excepted): ``(cat, cat_mag,
    cells)`` placed on every device once per database, and a dict of the keyword arguments.
    """
    cat_np = np.asarray(db.catalog.unit_vectors, np.float64)
    # every catalog star within the field's half diagonal of any boresight in a cell (frame coverage)
    index = build_sky_index(cat_np, db.camera.half_diagonal_rad,
                            key=f"sgm-frame-{db.catalog.fingerprint}")
    tables = on_every_device(db, "verify", lambda: (
        jnp.asarray(cat_np, jnp.float32), jnp.asarray(db.catalog.mag, jnp.float32),
        index.device_arrays()[0]))
    settings = dict(camera=db.camera, grid=index.grid,
                    k=float(config.verify.k), floor_deg=float(config.verify.floor_deg),
                    cap_deg=float(config.verify.cap_deg),
                    amb_k=float(config.verify.ambiguity_k),
                    amb_deg=float(config.verify.ambiguity_deg),
                    partner_joint=bool(config.verify.partner_joint),
                    partner_k=float(config.verify.partner_k),
                    mag_sigma=float(config.verify.magnitude_sigma or 0.0),
                    rms_z=float(config.verify.rms_z),
                    min_matched=int(config.min_matched),
                    min_coverage=float(config.verify.min_coverage),
                    n_near=int(min(2 * db.capacity, cat_np.shape[0])))
    return tables, settings


def _verify_scenes(xy, mag, valid, ids, ok, main, cat, cat_mag, cells, **settings):
    """:func:`.verify.verify_ids` with the scenes first, as :func:`jstarid.runtime.map_batch` splits them."""
    return verify_ids(cat, cat_mag, cells, xy, mag, valid, ids, ok, main, **settings)


def rename_and_reverify(db, scenes: Scene, verified: Identification, g: ImageGraph,
                        config: Config) -> Identification:
    """``Config.verify.rename``: :func:`name_leftovers` on the verified names, then :func:`verify_claims`
    again on the scenes it changed; where that fails, the first result stands. Returns an
    :class:`~jstarid.scene.Identification` with the same ``ok`` as ``verified``.
    """
    before = np.asarray(verified.ids)
    ids = name_leftovers(db, scenes, verified, g, config)
    changed = np.any(ids != before, axis=1)
    if not np.any(changed):
        return verified
    # verified again: only the scenes the renaming changed (the others keep their names)
    proposal = Identification(ids=jnp.asarray(ids), ok=jnp.asarray(np.asarray(verified.ok) & changed),
                              attitude=None)
    again, _ = verify_claims(db, scenes, proposal, g.main, config)
    take = changed & np.asarray(again.ok)
    ids = np.where(take[:, None], np.asarray(again.ids), before)
    return Identification(ids=jnp.asarray(ids), ok=verified.ok, attitude=None)


def check_vertices(adj_i, db_adj, res: SearchOutcome, config: Config) -> tuple[np.ndarray, np.ndarray]:
    """Unname matched vertices whose median edge residual exceeds ``config.vertex_check_deg``.

    Args:
        adj_i: (B, K, K) image adjacencies (deg). db_adj: (D, K, K) database adjacencies (deg).
        res: :class:`.search.SearchOutcome` (``match``, ``best``, ``ok``). config: :class:`Config`.

    Returns:
        ``(match, ok)``: (B, K) the kept correspondence (−1 elsewhere), (B,) bool.
    """
    match, ok = res.match.copy(), res.ok.copy()
    rows = np.nonzero(ok)[0]
    if rows.size == 0:
        return match, ok
    m = match[rows]
    used = m >= 0
    mj = np.clip(m, 0, None)
    a_j = db_adj[res.best[rows][:, None, None], mj[:, :, None], mj[:, None, :]]
    d = np.abs(adj_i[rows] - a_j)
    both = used[:, :, None] & used[:, None, :]
    both &= ~np.eye(m.shape[1], dtype=bool)[None]
    d = np.where(both, d, np.nan)
    with warnings.catch_warnings():  # all-NaN rows (unmatched vertices) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        resid = np.nanmedian(d, axis=2)
    bad = used & ~(resid <= config.vertex_check_deg)
    m = np.where(bad, -1, m)
    match[rows] = m
    ok[rows] = np.sum(m >= 0, axis=1) >= config.min_matched
    match[~ok] = -1
    return match, ok


def name_leftovers(db, scenes: Scene, result: Identification, g: ImageGraph, config: Config) -> np.ndarray:
    """(B, N) int32 ids: ``result.ids`` plus, in every successful scene, each unnamed image-graph member
    whose ICRS direction (``Cᵀ v``, attitude of the matched stars) lies within
    ``config.leftover_tol_deg`` of a catalog star not yet named in that scene.

    The rule is greedy, in member order: each member takes its nearest catalog star (float64
    cosines) when it lies within the tolerance and neither the match nor an earlier member has
    named it. Why not the shared :func:`jstarid.completion.name_stars`: it names other stars. It
    also asks the second-nearest star to lie beyond the tolerance, leaves unnamed both members
    that want one star, and compares float32 cosines and atan2 distances; so where a second
    catalog star lies within ``leftover_tol_deg`` or two members share a nearest star, the two
    rules disagree, and the verification and the whole-circle test read these names.
    """
    ids = np.array(result.ids)
    att, _, have = estimate_attitude(db.catalog, db.camera, scenes, result, min_stars=3)
    att, have = np.asarray(att, np.float64), np.asarray(have) & np.asarray(result.ok)
    vec = np.asarray(db.camera.unproject(scenes.xy), np.float64)  # (B, N, 3) camera frame
    cat = np.asarray(db.catalog.unit_vectors, np.float64)
    cos_tol = np.cos(np.radians(config.leftover_tol_deg))
    for s in np.nonzero(have)[0]:
        mem = g.members[s][g.mask[s]]
        todo = mem[ids[s, mem] < 0]
        if todo.size == 0:
            continue
        sky = np.matmul(vec[s, todo], att[s])  # rows: Cᵀ v, ICRS
        dots = np.matmul(sky, cat.T)  # (n_todo, catalog)
        best = np.argmax(dots, axis=1)
        used = set(ids[s][ids[s] >= 0].tolist())
        for det, row, dot in zip(todo, best, dots[np.arange(todo.size), best], strict=True):
            if dot >= cos_tol and int(row) not in used:
                ids[s, det] = row
                used.add(int(row))
    return ids


def attitude_from_names(db, scenes: Scene, result: Identification) -> Identification:
    """``result`` with the Wahba attitude of its names (``Identification.attitude`` (B, 3, 3); NaN
    where the scene is not solved or has too few names)."""
    att, _, have = estimate_attitude(db.catalog, db.camera, scenes, result)
    att = jnp.where((have & result.ok)[:, None, None], att, jnp.nan)
    return Identification(ids=result.ids, ok=result.ok, attitude=att)
