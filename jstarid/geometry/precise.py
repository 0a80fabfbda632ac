"""Matrix products at full float32 precision, whatever the backend (every geometric product uses these).

``jnp.matmul``, ``@`` and ``jnp.einsum`` run at the backend's *default* precision, and on recent NVIDIA
GPUs (Ampere and later, H100 included) JAX's default for float32 operands is TensorFloat-32: a 10-bit
mantissa, a relative error of ≈ 5·10⁻⁴ (JAX docs, "Matmul precision"). In geometry that is far too
coarse: a rotated unit vector off by 5·10⁻⁴ rad is ≈ 1.5 px on a 20° / 1024 px tracker, and a cosine
compared with cos 6° off by 5·10⁻⁴ moves a neighbor-circle boundary by ≈ 0.3°. On CPU the default is
already float32, so the CPU test suite cannot show the difference; these wrappers ask for
``Precision.HIGHEST`` (true float32) explicitly so that the numbers do not depend on the device.

Only the RpNet network (:mod:`jstarid.algorithms.rpnet.model`) keeps the default or bfloat16 products:
a neural network's inputs and weights carry far less precision than TF32 drops. A test
(``tests/geometry/test_precise.py``) checks that no other library code calls ``@``, ``jnp.matmul``,
``jnp.einsum`` or ``jnp.dot`` directly.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["PRECISION", "einsum", "matmul", "small_matmul"]

PRECISION = jax.lax.Precision.HIGHEST

matmul = functools.partial(jnp.matmul, precision=PRECISION)
matmul.__doc__ = "``jnp.matmul`` at full float32 precision on every backend (module docstring)."

einsum = functools.partial(jnp.einsum, precision=PRECISION)
einsum.__doc__ = "``jnp.einsum`` at full float32 precision on every backend (module docstring)."


def small_matmul(a, b):
    """``a @ b`` for a contraction over at most 3 terms (rotations, dot products of unit vectors),
    written out as float32 products and sums.

    Exact float32 on every backend like :data:`matmul` (elementwise arithmetic has no TF32 mode), and
    on CPU it fuses with what consumes it — a nearest-star search reduces the (N, M) cosines as they
    are made — where a ``dot_general`` with a 3-long contraction is handed to a matrix library and
    written out whole first (in RpNet's verification loop, ≈ 3 % faster identification); results
    agree with :data:`matmul` to float32 rounding.

    Args:
        a: (..., K) with K ≤ 3.
        b: (K, M).

    Returns:
        (..., M) float32.
    """
    k = a.shape[-1]
    if k > 3 or b.ndim != 2 or b.shape[0] != k:
        raise ValueError(f"small_matmul takes (..., K ≤ 3) @ (K, M), got {a.shape} @ {b.shape}")
    lead = (1,) * (a.ndim - 1)
    out = a[..., 0, None] * b[0].reshape(lead + (-1,))
    for i in range(1, k):
        out = out + a[..., i, None] * b[i].reshape(lead + (-1,))
    return out
