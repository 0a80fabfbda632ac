"""Neighbor graphs (You et al. 2022, "Database generation", Fig. 3) and their MST weight.

Vertices: the main star and every star within the neighbor-circle radius r of it; edge weights:
angular separations (deg). Stored padded to K vertices: vertices first (main star = vertex 0), a
(K,) mask, and a (K, K) adjacency that is 0 on the padding.

Algorithm 1's first step on a batch of scenes is :func:`searchable_graphs`: each scene's main star
(the detection nearest the principal point), its image graph G_I and w_I (:func:`scene_graphs`),
and which scenes can be searched at all.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.algorithms.sgm.config import Config
from jstarid.geometry.angles import angle_between
from jstarid.metrics import by_distance_to_principal_point, nearest_to_principal_point
from jstarid.runtime.program_store import stored_jit
from jstarid.scene import Scene

__all__ = ["separation_deg", "adjacency_deg", "plane_coords", "mst_weight", "image_graph", "scene_graphs",
           "searchable_graphs"]


def separation_deg(u, v):
    """Angle (deg) between unit vectors ``u`` (..., 3) and ``v`` (..., 3) by
    :func:`jstarid.geometry.angle_between` (float32 ``arccos`` near 1 is coarse to ~0.02°).
    """
    return jnp.degrees(angle_between(u, v))


def adjacency_deg(vecs, mask):
    """Adjacency matrix A(i, k) = θ_ik (deg) of the vertices ``vecs`` (K, 3); 0 where masked."""
    a = separation_deg(vecs[:, None, :], vecs[None, :, :])
    keep = mask[:, None] & mask[None, :]
    return jnp.where(keep, a, 0.0)


def plane_coords(vecs, mask):
    """Azimuthal equidistant coordinates (deg) of the vertices about vertex 0 (the main star).

    Radius = the angle to the main star (exact), azimuth measured in a basis perpendicular to it
    that is built the same way on both sides (a right-handed frame stays right-handed), so an image
    graph and its database graph differ by a rotation about the origin plus noise; the tangential
    scale error is ≈ r²/6 (0.01° at r = 6°). Read by the triangle screen (:mod:`.screen`).

    Args:
        vecs: (K, 3) unit vectors, vertex 0 the main star. mask: (K,) bool vertices present.

    Returns:
        (K, 2) float32 (x, y) in deg, 0 on padding.
    """
    u0 = vecs[0]
    # a reference axis far from u0 (the smallest |component|), then e1 ⟂ u0, e2 = u0 × e1
    ref = jnp.eye(3, dtype=vecs.dtype)[jnp.argmin(jnp.abs(u0))]
    e1 = jnp.cross(ref, u0)
    e1 = e1 / jnp.linalg.norm(e1)
    e2 = jnp.cross(u0, e1)
    x = jnp.sum(vecs * e1[None, :], axis=-1)
    y = jnp.sum(vecs * e2[None, :], axis=-1)
    r = separation_deg(vecs, u0[None, :])
    az = jnp.arctan2(y, x)
    xy = jnp.stack([r * jnp.cos(az), r * jnp.sin(az)], axis=-1)
    return jnp.where(mask[:, None], xy, 0.0).astype(jnp.float32)


def mst_weight(adj, mask):
    """Total edge weight of the minimum spanning tree of a padded complete graph (Prim).

    Dense Prim in K − 1 fixed steps (masked once the tree is complete), so it jits and vmaps; the
    paper's Kruskal gives the same total.

    Args:
        adj: (K, K) symmetric edge weights (deg); only entries between masked-in vertices are read.
        mask: (K,) bool vertices present. Vertex 0 must be present unless the graph is empty.

    Returns:
        () total MST weight w (deg); 0 for graphs of 0 or 1 vertex.
    """
    k = adj.shape[0]
    inf = jnp.asarray(jnp.inf, adj.dtype)
    in_tree = jnp.zeros((k,), bool).at[0].set(mask[0])
    dist = jnp.where(mask & mask[0], adj[0], inf)

    def body(_, carry):
        in_tree, dist, total = carry
        cand = jnp.where(mask & ~in_tree, dist, inf)
        v = jnp.argmin(cand)
        d = cand[v]
        ok = jnp.isfinite(d)
        total = total + jnp.where(ok, d, 0.0)
        in_tree = in_tree.at[v].set(in_tree[v] | ok)
        dist = jnp.where(ok & mask, jnp.minimum(dist, adj[v]), dist)
        return in_tree, dist, total

    _, _, total = jax.lax.fori_loop(0, k - 1, body, (in_tree, dist, jnp.zeros((), adj.dtype)))
    return total


class ImageGraph(NamedTuple):
    """Image neighbor graph(s) (leading batch axes, if any, on every field).

    Attributes:
        members: (…, K) int32 detection index of each vertex (main star first; −1 padding).
        mask: (…, K) bool real vertices. adj: (…, K, K) float32 adjacency A_I (deg, 0 on padding).
        n: (…,) int32 vertices. w: (…,) float32 MST weight w_I (deg).
        overflow: (…,) bool, more than K detections inside the circle (the graph is unusable).
        main: (…,) int32 detection index of the main star; ``any``: (…,) bool, the scene has a
            detection (both set by :func:`scene_graphs`; −1 and
            False for a lone graph).
        plane: (…, K, 2) float32 :func:`plane_coords` of the vertices (deg).
    """

    members: Any
    mask: Any
    adj: Any
    n: Any
    w: Any
    overflow: Any
    main: Any = -1
    any: Any = False
    plane: Any = None


def image_graph(vecs, valid, main, radius_deg: float, capacity: int):
    """The neighbor graph of detection ``main`` in one scene (You et al. 2022, "Rough search").

    Args:
        vecs: (N, 3) camera-frame unit vectors of the detections. valid: (N,) bool real detections.
        main: () int index of the main star (a valid detection).
        radius_deg: neighbor-circle radius r (deg). capacity: static K, vertex capacity.

    Returns:
        :class:`ImageGraph` of one scene (``members`` (K,), ``mask`` (K,), ``adj`` (K, K) deg, ``n``,
        ``w`` deg, ``overflow``): the main star first, then the others in scene order (brightest
        first); an overflowing graph is unusable.
    """
    n_det = vecs.shape[0]
    ang = separation_deg(vecs, vecs[main][None, :])
    idx = jnp.arange(n_det)
    inside = valid & (ang <= radius_deg) & valid[main]
    # main first, then the others inside in scene order, then everything else
    key = jnp.where(idx == main, 0, jnp.where(inside, 1, 2)) * n_det + idx
    order = jnp.argsort(key)
    take = order[:capacity] if n_det >= capacity else jnp.pad(order, (0, capacity - n_det))
    count = jnp.sum(inside)
    n = jnp.minimum(count, capacity)
    mask = jnp.arange(capacity) < n
    members = jnp.where(mask, take, -1).astype(jnp.int32)
    v = jnp.where(mask[:, None], vecs[jnp.clip(members, 0, n_det - 1)], 0.0)
    adj = adjacency_deg(v, mask)
    return ImageGraph(members=members, mask=mask, adj=adj.astype(jnp.float32), n=n.astype(jnp.int32),
                      w=mst_weight(adj, mask).astype(jnp.float32), overflow=count > capacity,
                      plane=plane_coords(v, mask))


@functools.partial(stored_jit, static_argnames=("camera", "radius_deg", "capacity", "main_rank"))
def scene_graphs(xy, valid, *, camera, radius_deg: float, capacity: int, main_rank: int = 0):
    """Image neighbor graphs of a batch.

    Args:
        xy: (B, N, 2) centroids (px). valid: (B, N) bool.
        camera: static :class:`~jstarid.camera.Camera`. radius_deg: r (deg). capacity: static K.
        main_rank: static; the main star is the valid detection nearest the principal point (0, the
            paper's choice) or the ``main_rank``-th nearest after it (``Config.subgraph.main_stars``).

    Returns:
        :class:`ImageGraph` of (B, …) arrays, with ``main`` (B,) int32 main-star detection and
        ``any`` (B,) bool (the scene has such a detection).
    """
    if main_rank == 0:
        main = nearest_to_principal_point(xy, valid, camera)
        has = jnp.any(valid, axis=-1)
    else:
        main = by_distance_to_principal_point(xy, valid, camera)[:, main_rank]
        has = jnp.sum(valid, axis=-1) > main_rank
    vecs = camera.unproject(xy)
    g = jax.vmap(image_graph, in_axes=(0, 0, 0, None, None))(vecs, valid, main, radius_deg,
                                                             capacity)
    return g._replace(main=main.astype(jnp.int32), any=has)


def searchable_graphs(db, scenes: Scene, config: Config, main_rank: int = 0):
    """The scenes' image graphs (:func:`scene_graphs`, as NumPy arrays) and which ones Algorithm 1
    searches: (B,) bool, a detection, no overflow, at least ``config.min_stars`` vertices."""
    g = jax.tree.map(np.asarray, scene_graphs(scenes.xy, scenes.valid, camera=db.camera,
                                              radius_deg=float(db.radius_deg), capacity=int(db.capacity),
                                              main_rank=main_rank))
    return g, g.any & ~g.overflow & (g.n >= config.min_stars)


def catalog_neighbors(unit_vectors: np.ndarray, row: int, radius_deg: float) -> np.ndarray:
    """Host helper: catalog rows of the neighbor graph of ``row`` (itself first, then by row)."""
    dots = np.matmul(unit_vectors, unit_vectors[row])
    near = np.nonzero(dots >= np.cos(np.radians(radius_deg)))[0]
    return np.concatenate([[row], near[near != row]]).astype(np.int32)
