"""RpNet initial input S_ori (§II-A, steps 1–4 and eq. 3), for one guide star; batch with ``vmap``.

For a guide star S and the other stars (unit vectors in any common frame):

1. the guiding neighbour stars (GNSs) are those with angular distance d_sn < ρ to S (eq. 2);
2. only the m nearest are kept (s-GNSs; fewer when fewer exist);
3. d_sn is binned with e, the neighbour–neighbour distances d_nn (each unordered pair once) with 2e
   (eq. 3); each adds 1 to its bin of D_sn or D_nn, both ⌊ρ/e⌋ long (rounding at the top edge is
   clipped into the last bin);
4. S_ori = [D_sn, D_nn] (2⌊ρ/e⌋ counts, no normalisation, as in the paper).

Rotation invariant (angles only). Serves training (catalog vectors) and inference (unprojected
centroids); the caller masks the guide out of the others.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from jstarid.algorithms.rpnet.config import Config
from jstarid.geometry.angles import angle_between
from jstarid.runtime.program_store import stored_jit

__all__ = ["config_kwargs", "initial_input", "scene_inputs"]


def initial_input(guide, others, mask, *, rho_rad: float, e_rad: float, m: int, n_bins: int):
    """Initial input S_ori of one guide star (eq. 3).

    Args:
        guide: (3,) unit vector of the guide star S.
        others: (N, 3) unit vectors of the other stars (same frame as ``guide``).
        mask: (N,) bool, True for real stars other than S (padding and S itself False).
        rho_rad: pattern radius ρ (rad).
        e_rad: discretization factor e (rad); D_nn uses 2e.
        m: number of nearest neighbours kept.
        n_bins: ⌊ρ/e⌋, the length of D_sn and D_nn.

    Returns:
        (2·n_bins,) float32 ``[D_sn, D_nn]`` (counts).
    """
    d = angle_between(guide[None, :], others)  # (N,) d_sn, eq. 2
    gns = mask & (d < rho_rad)
    k = min(m, others.shape[0])
    neg, idx = jax.lax.top_k(-jnp.where(gns, d, jnp.inf), k)  # m nearest GNSs (step 2)
    keep = jnp.isfinite(neg)  # fewer than m GNSs: the rest is padding
    d_sn = -jnp.where(keep, neg, 0.0)
    id1 = jnp.clip(jnp.floor(d_sn / e_rad).astype(jnp.int32), 0, n_bins - 1)  # eq. 3, bin e
    d_sn_hist = jnp.zeros((n_bins,), jnp.float32).at[id1].add(keep.astype(jnp.float32))

    sel = others[idx]  # (k, 3) s-GNSs
    d_nn = angle_between(sel[:, None, :], sel[None, :, :])  # (k, k)
    upper = jnp.triu(jnp.ones((k, k), bool), 1) & keep[:, None] & keep[None, :]
    id2 = jnp.clip(jnp.floor(d_nn / (2.0 * e_rad)).astype(jnp.int32), 0, n_bins - 1)  # eq. 3, bin 2e
    d_nn_hist = jnp.zeros((n_bins,), jnp.float32).at[id2.reshape(-1)].add(
        upper.reshape(-1).astype(jnp.float32))
    return jnp.concatenate([d_sn_hist, d_nn_hist])


def config_kwargs(config: Config) -> dict:
    """Static keyword arguments of :func:`initial_input` from a :class:`Config`."""
    return dict(rho_rad=math.radians(config.rho_deg), e_rad=math.radians(config.e_deg), m=config.m,
                n_bins=config.n_bins)


@functools.partial(stored_jit, static_argnames=("camera", "rho_rad", "e_rad", "m", "n_bins"))
def scene_inputs(xy, valid, guide_index, *, camera, rho_rad, e_rad, m, n_bins):
    """Initial inputs of chosen detections of a batch of scenes (inference side).

    Args:
        xy: (B, N, 2) centroids (px).
        valid: (B, N) bool detections.
        guide_index: (B, G) int32 detection index of each guide (G guides per scene).
        camera: :class:`~jstarid.camera.Camera` (static).

    Returns:
        (B, G, 2·n_bins) float32 inputs; the guide itself is left out of its own neighbours.
    """
    vec = camera.unproject(xy)  # (B, N, 3) camera frame

    def one_scene(vec_s, valid_s, g_s):
        n = vec_s.shape[0]

        def one_guide(g):
            mask = valid_s & (jnp.arange(n) != g)
            return initial_input(vec_s[g], vec_s, mask, rho_rad=rho_rad, e_rad=e_rad, m=m, n_bins=n_bins)

        return jax.vmap(one_guide)(g_s)

    return jax.vmap(one_scene)(vec, valid, guide_index)
