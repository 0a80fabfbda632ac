"""Padding the batch axis to a static size (the one padding rule of the runtime)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["call_padded", "call_size", "call_width", "coarse_size", "columns_in_use", "next_power_of_two",
           "pad_rows", "padded_indices", "power_of_two_chunks"]

MAX_PADDING = 0.25  # power_of_two_chunks: most padding of a last chunk, as a share of its rows
MIN_CALL_SIZE = 16  # call_size: the smallest call of a batched kernel (rows)
COARSE_STEP = 4  # coarse_size: each size of its ladder is this many times the one below
COARSE_SUB_BATCH = 128  # padded_indices(coarse=True): the largest coarse size (copies are computed)


def pad_rows(tree, size: int, *, mode: str = "zeros"):
    """Pad every leaf's leading axis to ``size``.

    Args:
        tree: pytree of NumPy or JAX arrays sharing the leading axis length n ≤ size (JAX arrays
            may be traced: the padding is static).
        size: the padded length.
        mode: ``"zeros"`` (empty scenes: zero coordinates, ``valid`` False) or ``"edge"`` (copies of
            the last row, for kernels that must see real-looking data).

    Returns:
        The padded pytree (the input itself where n == size).
    """
    if mode not in ("zeros", "edge"):
        raise ValueError(f"mode must be 'zeros' or 'edge', got {mode!r}")

    def pad(a):
        extra = size - a.shape[0]
        if extra < 0:
            raise ValueError(f"cannot pad {a.shape[0]} rows to {size}")
        if extra == 0:
            return a
        xp = np if isinstance(a, np.ndarray) else jnp
        if mode == "edge":
            return xp.concatenate([a, xp.broadcast_to(a[-1:], (extra, *a.shape[1:]))])
        return xp.pad(a, [(0, extra)] + [(0, 0)] * (a.ndim - 1))

    return jax.tree.map(pad, tree)


def next_power_of_two(n: float, floor: int = 1) -> int:
    """The smallest power of two ≥ ``n`` and ≥ ``floor``: the padded size of every variable-size batch,
    buffer and retry, so that a few static shapes (compilations) serve every call.

    Args:
        n: the size to hold (a float is rounded up; ≤ 1 gives 1).
        floor: the smallest size returned (a power of two).
    """
    return max(int(floor), 1 << max(math.ceil(n) - 1, 0).bit_length())


def call_padded(fn, batched: tuple, *args, floor: int = MIN_CALL_SIZE, limit: int | None = None,
                mode: str = "zeros", **kwargs):
    """``fn(*batched, *args, **kwargs)`` at a padded batch: the leading axis of ``batched`` padded
    (:func:`pad_rows`) to the next power of two ≥ ``floor``, every leaf of the output cut back to
    the B rows.

    Why: a kernel called on whole batches (a check, the outcome of each scene, the simulator's draw)
    compiled a program for every batch size it met; padded, one program serves every size of a
    bucket. ``fn`` must treat its rows independently, and a padding row must be harmless to it.

    Args:
        fn: the kernel; its output leaves all have the batch axis first.
        batched: tuple of pytrees whose leaves share the leading batch size B (≥ 0).
        *args, **kwargs: passed as they are (replicated arrays, static settings).
        floor: the smallest padded size.
        limit: batches of this many rows or more run as they are (a kernel that splits large
            batches itself); ``None``: every batch is padded.
        mode: :func:`pad_rows`' mode (``"edge"`` where a row of zeros is not valid input, e.g.
            PRNG keys).
    """
    b = jax.tree.leaves(batched)[0].shape[0]
    size = b if limit is not None and b >= limit else next_power_of_two(b, floor)
    if size == b:
        return fn(*batched, *args, **kwargs)
    out = fn(*pad_rows(batched, size, mode=mode), *args, **kwargs)
    return jax.tree.map(lambda a: a[:b], out)


def coarse_size(n: int, floor: int, limit: int) -> int:
    """The padded size of a call whose padding rows cost (almost) nothing — empty scenes no search
    visits, padding pairs a kernel skips: ``floor`` · 4^k up to ``limit``, powers of two above.

    Why: a sweep meets fresh scenes every call, and the sub-batches they leave (scenes retried with
    another main star or focal length, candidate pairs of one size) take a different size each call.
    Padded to powers of two, those sizes compiled new programs in most calls of a sweep; in steps of
    4 four sizes serve every call from 16 to 1,024 rows (powers of two take seven), so fresh
    batches meet sizes compiled already. Above ``limit`` the padding would cost more than a
    compilation saves.

    Args:
        n: rows to hold (≥ 0). floor: the smallest size (≥ 1). limit: the largest size of the coarse
            ladder (sizes above it are powers of two).

    Returns:
        The padded size (≥ n and ≥ ``floor``).
    """
    size = max(int(floor), 1)
    while size < n and size * COARSE_STEP <= limit:
        size *= COARSE_STEP
    return size if size >= n else max(size, next_power_of_two(n))


def call_size(n: int, chunk: int) -> int:
    """Rows per kernel call for a batch of ``n`` rows run in calls of at most ``chunk`` rows.

    The next power of two ≥ :data:`MIN_CALL_SIZE`, capped at ``chunk``: batches of 1, 3 or 12 scenes all run
    in calls of 16 and share one compilation, where a call of exactly ``n`` rows would compile a
    program per batch size (a small call's padding costs microseconds; a compilation, seconds).

    Args:
        n: rows of the batch (≥ 0).
        chunk: the most rows per call (``Config.batch_chunk``).
    """
    return max(1, min(int(chunk), next_power_of_two(n, floor=MIN_CALL_SIZE)))


def columns_in_use(valid) -> np.ndarray:
    """(B,) int: the columns each row of a (B, N) validity mask fills, one past its last valid entry
    (0 for an empty row): the width a call must keep when it cuts trailing padding columns."""
    valid = np.asarray(valid, bool)
    return np.where(valid.any(axis=1), valid.shape[1] - np.argmax(valid[:, ::-1], axis=1), 0)


def call_width(filled: np.ndarray, rows: np.ndarray, n: int, floor: int) -> int:
    """The columns a call of ``rows`` keeps when it cuts trailing padding columns: the most any of
    them fills (``filled``, :func:`columns_in_use`), as a power of two ≥ ``floor`` (a few widths, so
    a few programs), at most the ``n`` there are."""
    return min(int(n), next_power_of_two(int(np.max(filled[rows], initial=0)), floor=floor))


def padded_indices(rows: np.ndarray, floor: int = 1, *, coarse: bool = False) -> np.ndarray:
    """``rows`` (R,) (R ≥ 1) padded with copies of its first entry: the rows of a sub-batch gathered
    at a size that earlier calls have compiled.

    Args:
        rows: (R,) row indices. floor: the smallest padded size.
        coarse: pad to :func:`coarse_size` up to :data:`COARSE_SUB_BATCH` rows (16, 64, then powers
            of two) instead of :func:`next_power_of_two`: for a sub-batch the data sizes anew in
            every call (the scenes a retry takes up, the claims to verify), where a padding row
            costs little next to a compilation.
    """
    rows = np.asarray(rows)
    size = (coarse_size(rows.size, floor, COARSE_SUB_BATCH) if coarse
            else next_power_of_two(rows.size, floor))
    return np.concatenate([rows, np.full(size - rows.size, rows[0])])


def power_of_two_chunks(n: int, floor: int, max_padding: float = MAX_PADDING) -> list[tuple[int, int, int]]:
    """Cut n rows into calls whose padded sizes are powers of two ≥ ``floor``, with little padding.

    One call padded to the next power of two wastes up to half of its work (5,000 rows → 8,192);
    taking the largest power of two that fits instead, until the rest pads by at most
    ``max_padding`` of itself, wastes little more than that share (5,000 → 4,096 + 1,024) and
    uses no other sizes, so no other compilations.

    Args:
        n: rows (≥ 0). floor: smallest padded size (a power of two).
        max_padding: the padding a last call may add, as a share of its real rows.

    Returns:
        ``[(lo, hi, padded), …]``: consecutive slices covering ``range(n)``, ``padded ≥ hi − lo``.
    """
    out, lo = [], 0
    while lo < n:
        rest = n - lo
        padded = max(floor, 1 << (rest - 1).bit_length())
        if padded == floor or padded - rest <= max_padding * rest:
            out.append((lo, n, padded))
            break
        out.append((lo, lo + padded // 2, padded // 2))
        lo += padded // 2
    return out
