"""Counter-based random streams for the simulator: Threefry-2x32 written out in ``jnp``.

JAX lowers its Threefry hash to a 5-step ``while`` loop on CPU; inside the simulator's vmapped chunks
that loop cannot fuse with its consumers and costs more than the rest of the scene. Written out, the
hash fuses with the uniform → normal transform into one vectorised loop. :func:`threefry2x32` is
bit-identical to ``jax.extend.random.threefry_2x32`` (tested), :func:`unit_uniform` to
``jax.random.uniform``'s bits → float transform and :func:`normals` to ``jax.random.normal``'s.

A scene has a seed (:func:`scene_seed`, a (2,) uint32 Threefry key) and one counter stream per kind
of draw (the constants below): word i of a stream is Threefry(seed, (i, stream)), so a draw of n
values is a prefix of any longer draw of the same stream.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["threefry2x32", "scene_seed", "words", "unit_uniform", "unit_normal", "uniforms", "normals",
           "POSITION", "MAG", "MISSING", "FALSE_XY", "FALSE_MAG", "FALSE_R", "FALSE_T", "FLUX"]


def threefry2x32(k0, k1, x0, x1):
    """Threefry-2x32 (20 rounds), bit-identical to ``jax.extend.random.threefry_2x32``, unrolled.

    All arguments are uint32 arrays (broadcast together); returns the two output words.
    """
    def rotl(v, r):
        return (v << np.uint32(r)) | (v >> np.uint32(32 - r))

    ks = (k0, k1, k0 ^ k1 ^ np.uint32(0x1BD11BDA))
    rotations = ((13, 15, 26, 6), (17, 29, 16, 24))
    x0, x1 = x0 + ks[0], x1 + ks[1]
    for i in range(5):
        for r in rotations[i % 2]:
            x0 = x0 + x1
            x1 = rotl(x1, r) ^ x0
        x0 = x0 + ks[(i + 1) % 3]
        x1 = x1 + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x0, x1


# Counter streams of a scene's seed (the second Threefry input word): one per kind of draw.
POSITION, MAG, MISSING, FALSE_XY, FALSE_MAG = 1, 2, 3, 4, 5
FALSE_R, FALSE_T = 6, 7
FALSE_COUNT = 8
FLUX = 9  # the detection model's flux measurement (jstarid.detection_model)


def scene_seed(key):
    """(2,) uint32 Threefry key for a scene's steps 2–7, derived from the scene key."""
    if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        data = jax.random.key_data(key)
    else:  # legacy uint32 key
        data = jnp.asarray(key, jnp.uint32)
    if data.shape != (2,):  # another key implementation: draw a Threefry key from it
        data = jax.random.bits(key, (2,), jnp.uint32)
    # hashed once so the streams below share no counter with jax.random's use of the scene key
    return jnp.stack(threefry2x32(data[0], data[1], np.uint32(0x243F6A88), np.uint32(0x85A308D3)))


def words(seed, stream, n):
    """Random uint32 words of one stream of a scene.

    Word i (row-major position) is the first output word of Threefry(seed, (i, stream)), so for a
    1-d ``n`` the first m words are the same for any n ≥ m: a scene gets identical noise whatever
    candidate-list width its chunk uses. (Using both output words would halve the hashing, but
    interleaving them defeats XLA's vectorisation, and the hash is the cheap part next to the normal
    transform.)

    Args:
        seed: (2,) uint32 scene seed (:func:`scene_seed`).
        stream: static int, the kind of draw (one of the ``_STREAM_*`` constants).
        n: static int or shape tuple.

    Returns:
        uint32 array of shape ``(n,)`` or ``n``.
    """
    shape = (n,) if isinstance(n, int) else tuple(n)
    # row-major counters of an n-d shape, built from iotas (a reshaped arange would not fuse as well)
    count = jnp.zeros(shape, jnp.uint32)
    for d in range(len(shape)):
        count = count * np.uint32(shape[d]) + jax.lax.broadcasted_iota(jnp.uint32, shape, d)
    return threefry2x32(seed[0], seed[1], count, np.uint32(stream))[0]


def unit_uniform(words):
    """uint32 words → float32 uniforms in [0, 1) (23 random mantissa bits, as ``jax.random.uniform``)."""
    bits = jax.lax.shift_right_logical(words, jnp.uint32(9)) | jnp.uint32(0x3F800000)
    return jax.lax.bitcast_convert_type(bits, jnp.float32) - 1.0


def uniforms(seed, stream, n):
    """float32 uniforms in [0, 1) of shape ``(n,)`` or ``n``, prefix-stable in n (see :func:`words`)."""
    return unit_uniform(words(seed, stream, n))


def unit_normal(words):
    """uint32 words → standard normal float32 draws, ``jax.random.normal``'s transform: √2 · erfinv(u)
    with u uniform in (−1, 1), u's lower end nudged off −1 as JAX does."""
    lo = np.nextafter(np.float32(-1.0), np.float32(0.0))
    u = jnp.maximum(lo, unit_uniform(words) * (1.0 - lo) + lo)
    return np.float32(math.sqrt(2.0)) * jax.lax.erf_inv(u)


def normals(seed, stream, n):
    """Standard normal float32 draws of shape ``(n,)`` or ``n``, prefix-stable in n (:func:`words`)."""
    return unit_normal(words(seed, stream, n))
