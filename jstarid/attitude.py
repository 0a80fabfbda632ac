"""Attitude utilities: random rotations, conversions at the API edge, Wahba's problem, errors.

An attitude is a rotation matrix ``C`` taking ICRS vectors into the camera frame, ``v_cam = C @ r``
(docs/conventions.md §1). Its rows are the camera axes expressed in ICRS; row 2 is the boresight.

(RA, Dec, roll) convention: the boresight points at (α, δ); with roll φ = 0 the camera +x axis points
east (increasing α) and +y north, and a positive roll turns +x towards north:
``x = cos φ·east + sin φ·north``, ``y = −sin φ·east + cos φ·north``, ``z = x × y = boresight``.

Quaternions are scalar-last ``(x, y, z, w)`` as in ``scipy.spatial.transform.Rotation`` and describe
the same rotation as ``C`` (``Rotation.from_quat(q).as_matrix() == C``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jstarid.camera import Camera
from jstarid.geometry import precise
from jstarid.geometry.small_linalg import nearest_rotation
from jstarid.runtime.batching import chunk_calls, run_calls, take_rows
from jstarid.runtime.devices import batch_mesh
from jstarid.runtime.padding import call_size
from jstarid.runtime.program_store import stored_jit

__all__ = [
    "random_rotation", "rotation_from_boresight", "rotation_to_radec_roll",
    "rotation_from_radec_roll", "quaternion_from_rotation", "rotation_from_quaternion",
    "solve_wahba", "triad", "attitude_errors_arcsec", "estimate_attitude",
]

_RAD_TO_ARCSEC = 180.0 / jnp.pi * 3600.0
ESTIMATE_CHUNK = 1024  # scenes per call of estimate_attitude (padded to a power of two ≥ 16)


def rotation_from_quaternion(q):
    """(..., 4) scalar-last quaternions (any norm > 0) → (..., 3, 3) rotation matrices."""
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def quaternion_from_rotation(c):
    """(..., 3, 3) rotation matrices → (..., 4) scalar-last unit quaternions with w ≥ 0.

    Shepperd's method: pick the largest of the four squared components for numerical stability.
    """
    c = jnp.asarray(c)
    tr = c[..., 0, 0] + c[..., 1, 1] + c[..., 2, 2]
    cand = jnp.stack([
        jnp.stack([1 + 2 * c[..., 0, 0] - tr, c[..., 0, 1] + c[..., 1, 0],
                   c[..., 0, 2] + c[..., 2, 0], c[..., 2, 1] - c[..., 1, 2]], -1),
        jnp.stack([c[..., 0, 1] + c[..., 1, 0], 1 + 2 * c[..., 1, 1] - tr,
                   c[..., 1, 2] + c[..., 2, 1], c[..., 0, 2] - c[..., 2, 0]], -1),
        jnp.stack([c[..., 0, 2] + c[..., 2, 0], c[..., 1, 2] + c[..., 2, 1],
                   1 + 2 * c[..., 2, 2] - tr, c[..., 1, 0] - c[..., 0, 1]], -1),
        jnp.stack([c[..., 2, 1] - c[..., 1, 2], c[..., 0, 2] - c[..., 2, 0],
                   c[..., 1, 0] - c[..., 0, 1], 1 + tr], -1),
    ], axis=-2)  # (..., 4 choices, 4 components); choice k has component k = 4 q_k²·... largest
    diag = jnp.stack([cand[..., 0, 0], cand[..., 1, 1], cand[..., 2, 2], cand[..., 3, 3]], -1)
    best = jnp.argmax(diag, axis=-1)
    q = jnp.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return q * jnp.where(q[..., 3:4] < 0, -1.0, 1.0)


def random_rotation(key, shape=()):
    """Rotations uniform over SO(3) (Haar measure): normalized 4-D Gaussian quaternions.

    Args:
        key: PRNG key.
        shape: batch shape.

    Returns:
        (*shape, 3, 3) float32 rotation matrices.
    """
    return rotation_from_quaternion(jax.random.normal(key, (*shape, 4), dtype=jnp.float32))


def _east_north(boresight):
    """Local east and north unit vectors at ICRS unit vectors (..., 3); safe at the poles."""
    x, y = boresight[..., 0], boresight[..., 1]
    rho = jnp.sqrt(x * x + y * y)
    at_pole = rho < 1e-9
    safe_rho = jnp.where(at_pole, 1.0, rho)
    # At a pole any east works; pick α = 0 so the convention is continuous with Dec → ±90°.
    east = jnp.where(at_pole[..., None], jnp.array([0.0, 1.0, 0.0], boresight.dtype),
                     jnp.stack([-y / safe_rho, x / safe_rho, jnp.zeros_like(x)], -1))
    north = jnp.cross(boresight, east)
    return east, north


def rotation_from_boresight(boresight, roll):
    """Attitude with the camera +z on ``boresight`` and roll φ (rad) as in the module doc.

    Args:
        boresight: (..., 3) ICRS unit vectors.
        roll: (...,) rad.

    Returns:
        (..., 3, 3) rotation matrices (rows: camera x, y, z axes in ICRS).
    """
    east, north = _east_north(boresight)
    cr, sr = jnp.cos(roll)[..., None], jnp.sin(roll)[..., None]
    x_axis = cr * east + sr * north
    y_axis = -sr * east + cr * north
    return jnp.stack([x_axis, y_axis, boresight], axis=-2)


def rotation_from_radec_roll(ra, dec, roll):
    """(RA, Dec, roll) in rad → (..., 3, 3) rotation matrices."""
    ra, dec = jnp.asarray(ra), jnp.asarray(dec)
    bore = jnp.stack([jnp.cos(ra) * jnp.cos(dec), jnp.sin(ra) * jnp.cos(dec), jnp.sin(dec)], -1)
    return rotation_from_boresight(bore, jnp.asarray(roll))


def rotation_to_radec_roll(c):
    """(..., 3, 3) rotation matrices → (ra ∈ [0, 2π), dec, roll ∈ (−π, π]) in rad."""
    c = jnp.asarray(c)
    bore = c[..., 2, :]
    ra = jnp.mod(jnp.arctan2(bore[..., 1], bore[..., 0]), 2 * jnp.pi)
    dec = jnp.arcsin(jnp.clip(bore[..., 2], -1.0, 1.0))
    east, north = _east_north(bore)
    x_axis = c[..., 0, :]
    roll = jnp.arctan2(jnp.sum(x_axis * north, -1), jnp.sum(x_axis * east, -1))
    return ra, dec, roll


def triad(b1, b2, r1, r2):
    """Attitude C (``v_cam = C r``) from two vector pairs (TRIAD, Shuster & Oh 1981): exact on the
    first pair, the second fixes the roll about it.

    Args:
        b1, b2: (..., 3) unit vectors in the camera frame. r1, r2: (..., 3) their ICRS unit vectors.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    def frame(u, v):
        w = jnp.cross(u, v)
        w = w / jnp.linalg.norm(w, axis=-1, keepdims=True)
        return jnp.stack([u, w, jnp.cross(u, w)], -1)  # columns

    return precise.einsum("...ik,...jk->...ij", frame(b1, b2), frame(r1, r2))


def solve_wahba(body, ref, weights):
    """Weighted Wahba problem: the proper rotation C minimising Σ w ‖b − C r‖² (Markley 1988).

    C is the nearest rotation to B = Σ w b rᵀ (:func:`~jstarid.geometry.small_linalg.nearest_rotation`,
    Newton's polar iteration in plain array operations: LAPACK's batched SVD can hang XLA:CPU with
    several host devices, see that module). Both vector sets are first turned so that their weighted
    mean directions lie on +z: in a narrow field B is then ≈ diag(·, ·, Σw) plus terms of the stars'
    offsets from the mean, each summed from small numbers, where the plain B = Σ w b rᵀ rounds those
    small singular values (≈ Σw·θ², θ the field radius) against its ≈ Σw entries in float32. C is
    that solution turned back.

    Args:
        body: (..., n, 3) unit vectors in the camera frame.
        ref: (..., n, 3) matching ICRS unit vectors.
        weights: (..., n) non-negative weights (0 masks a pair out).

    Returns:
        (..., 3, 3) proper rotation ``C`` (det +1). With fewer than two independent pairs the answer
        is not unique; callers check the count.
    """
    turn_b = _mean_direction_frame(body, weights)
    turn_r = _mean_direction_frame(ref, weights)
    b_mat = precise.einsum("...n,...ni,...nj->...ij", weights,
                           precise.einsum("...ij,...nj->...ni", turn_b, body),
                           precise.einsum("...ij,...nj->...ni", turn_r, ref))
    return precise.einsum("...ji,...jk,...kl->...il", turn_b, nearest_rotation(b_mat), turn_r)


def _mean_direction_frame(vectors, weights):
    """(..., 3, 3) rotation taking the weighted mean direction of ``vectors`` (..., n, 3) to +z
    (+z itself where the weights are all 0)."""
    # a dot_general and written-out sums: XLA's reduce sums in an order that depends on the batch
    # shape, and an attitude must not depend on its batch
    mean = precise.einsum("...n,...ni->...i", weights, vectors)
    norm = jnp.sqrt(mean[..., :1] ** 2 + mean[..., 1:2] ** 2 + mean[..., 2:] ** 2)
    z = jnp.zeros_like(mean).at[..., 2].set(1.0)
    mean = jnp.where(norm > 0, mean / jnp.where(norm > 0, norm, 1.0), z)
    return rotation_from_boresight(mean, jnp.zeros(mean.shape[:-1], mean.dtype))


def attitude_errors_arcsec(c_est, c_true):
    """Boresight and roll errors (arcsec) between attitudes (..., 3, 3).

    Boresight error: angle between the two +z axes. Roll error: the rotation about the boresight of
    ``C_est C_trueᵀ`` (atan2 of its in-plane part), absolute value.

    Returns:
        ``(boresight_err, roll_err)``, each (...,) arcsec.
    """
    z_est, z_true = c_est[..., 2, :], c_true[..., 2, :]
    cross = jnp.linalg.norm(jnp.cross(z_est, z_true), axis=-1)
    dot = jnp.sum(z_est * z_true, axis=-1)
    bore = jnp.arctan2(cross, dot)
    delta = precise.einsum("...ij,...kj->...ik", c_est, c_true)
    roll = jnp.abs(jnp.arctan2(delta[..., 0, 1] - delta[..., 1, 0], delta[..., 0, 0] + delta[..., 1, 1]))
    return bore * _RAD_TO_ARCSEC, roll * _RAD_TO_ARCSEC


def estimate_attitude(catalog, camera, scenes, result, *, min_stars: int = 2):
    """Attitude from identified stars (Wahba / SVD), batched.

    Args:
        catalog: :class:`~jstarid.catalog.Catalog` whose rows ``result.ids`` refers to.
        camera: :class:`~jstarid.camera.Camera` of the scenes.
        scenes: :class:`~jstarid.scene.Scene` (B, N).
        result: :class:`~jstarid.scene.Identification` (B, N).
        min_stars: fewest identified stars for an attitude (2 fixes a rotation).

    Returns:
        ``(C, residual_arcsec, have)``: (B, 3, 3) float32 attitudes (NaN where ``have`` is False),
        (B,) RMS angle between measured and rotated catalog vectors (arcsec), (B,) bool.
    """
    # host arrays in calls of power-of-two sizes (the algorithms' call plan), the names' vectors
    # gathered here and the camera as traced numbers: a few programs serve every batch size, camera
    # and catalog
    xy, valid, ids = (np.asarray(a) for a in (scenes.xy, scenes.valid, result.ids))
    vectors = np.asarray(catalog.unit_vectors, np.float32)
    batched = (xy.astype(np.float32), valid & (ids >= 0), vectors[np.clip(ids, 0, len(vectors) - 1)])
    calls = chunk_calls(np.arange(ids.shape[0]), ESTIMATE_CHUNK, size=lambda n: call_size(n, ESTIMATE_CHUNK))
    out = run_calls(_estimate, calls, functools.partial(take_rows, batched), (camera.pinhole_numbers(),),
                    n_rows=ids.shape[0], tails=[(3, 3), (), ()],
                    fills=[np.float32(np.nan), np.float32(np.nan), False],
                    static=dict(min_stars=int(min_stars)), mesh=batch_mesh(jax.devices()[:1]))
    return tuple(jax.device_put(a) for a in out)


@functools.partial(stored_jit, static_argnames=("min_stars",))
def _estimate(xy, use, ref, optics, *, min_stars):
    """:func:`estimate_attitude` of a call: xy (B, N, 2) px, use (B, N) bool, ref (B, N, 3) the
    names' ICRS vectors, optics the camera's :meth:`~jstarid.camera.Camera.pinhole_numbers`."""
    body = Camera.traced(optics).unproject(xy)
    w = use.astype(jnp.float32)
    c = solve_wahba(body, ref, w)
    pred = precise.einsum("bij,bnj->bni", c, ref)
    ang = jnp.arctan2(jnp.linalg.norm(jnp.cross(pred, body), axis=-1), jnp.sum(pred * body, -1))
    n = jnp.sum(w, -1)
    rms = jnp.sqrt(jnp.sum(w * ang**2, -1) / jnp.maximum(n, 1.0)) * _RAD_TO_ARCSEC
    have = n >= min_stars
    c = jnp.where(have[:, None, None], c, jnp.nan)
    return c, jnp.where(have, rms, jnp.nan), have
