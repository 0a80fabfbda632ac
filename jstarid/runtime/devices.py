"""Sharding the batch axis over every device.

``map_batch(fn, batched, replicated)`` runs a per-batch function with its leading (batch) axis split
across a 1-D device mesh (``jax.shard_map``): each device processes its slice of the scenes with the
same code, and replicated arguments (catalog tables, databases) are copied to every device (once
per owner with :class:`~jstarid.runtime.DeviceCache`). The batch is padded to a multiple of the
device count and the padding dropped afterwards, so the result equals the single-device call
exactly. On one device it simply calls ``fn``.
"""

from __future__ import annotations

import functools
import os

import jax
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from jstarid.runtime.padding import pad_rows
from jstarid.runtime.program_store import storable_name, stored

__all__ = ["batch_mesh", "shard_batch", "replicate", "map_batch", "use_cpu_cores"]

BATCH_AXIS = "batch"


def use_cpu_cores(n: int | None = None) -> int:
    """Expose ``n`` CPU cores (default: all) as n JAX host devices, so :func:`map_batch` runs on each.

    JAX gives a CPU one device by default, and a computation made of many small matrix products
    (SGM's per-pair spectral matching) then leaves the other cores mostly idle. This sets
    ``--xla_force_host_platform_device_count`` in ``XLA_FLAGS``, which JAX reads when its backend
    starts: call it before the first JAX computation (scripts call it first thing; importing
    ``jstarid`` does not start the backend). An explicit count already in ``XLA_FLAGS`` (e.g. the
    test suite's) is left alone.

    Caution for kernels of your own: with several host devices, a large batched LAPACK call
    (``jnp.linalg.svd``, ``solve``, ``eigh``, …) can hang XLA:CPU for good, every pool thread waiting
    on chunks none is free to run; jstarid's kernels use :mod:`jstarid.geometry.small_linalg`.

    Returns:
        The device count requested (or the one already set).

    Raises:
        RuntimeError: the JAX backend has already started with another device count.
    """
    flag = "--xla_force_host_platform_device_count"
    flags = os.environ.get("XLA_FLAGS", "")
    if flag in flags:
        return int(flags.split(flag + "=")[1].split()[0])
    n = int(n or os.cpu_count() or 1)
    from jax._src import xla_bridge  # no public test for "backend started" (jax 0.10)

    if xla_bridge.backends_are_initialized():
        if jax.device_count() != n and jax.default_backend() == "cpu":
            raise RuntimeError("use_cpu_cores must run before the first JAX computation")
        return jax.device_count()
    os.environ["XLA_FLAGS"] = f"{flags} {flag}={n}".strip()
    return n


def batch_mesh(devices=None) -> jax.sharding.Mesh:
    """A 1-D mesh named ``"batch"`` over ``devices`` (default: all devices)."""
    devices = jax.local_devices() if devices is None else list(devices)
    return jax.sharding.Mesh(np.asarray(devices), (BATCH_AXIS,))


def shard_batch(tree, mesh=None):
    """Place every leaf's leading axis across the mesh (its length must divide evenly)."""
    mesh = batch_mesh() if mesh is None else mesh
    sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))
    return jax.tree.map(lambda a: jax.device_put(a, sharding), tree)


def replicate(tree, mesh=None):
    """Copy every leaf to every device of the mesh (arrays that each device reads whole)."""
    mesh = batch_mesh() if mesh is None else mesh
    sharding = NamedSharding(mesh, PartitionSpec())
    return jax.tree.map(lambda a: jax.device_put(a, sharding), tree)


def map_batch(fn, batched, replicated=(), *, static=None, mesh=None):
    """``fn(*batched, *replicated, **static)`` with the batch axis of ``batched`` sharded.

    Args:
        fn: a module-level function of (batched..., replicated..., **static) returning a pytree
            whose leaves all have the batch axis first; it must treat scenes independently.
        batched: tuple of pytrees whose leaves share the leading batch size B.
        replicated: tuple of pytrees copied to every device.
        static: hashable keyword arguments (compile-time constants). The compiled function is cached
            on ``(fn, static, mesh)``, so repeated calls do not recompile.
        mesh: a 1-D mesh (default: :func:`batch_mesh`).

    Returns:
        ``fn``'s output for all B scenes, sharded over the mesh.
    """
    mesh = batch_mesh() if mesh is None else mesh
    static = {} if static is None else static
    n_dev = mesh.devices.size
    if n_dev == 1:
        return fn(*batched, *replicated, **static)
    b = jax.tree.leaves(batched)[0].shape[0]
    total = -(-b // n_dev) * n_dev
    batched = pad_rows(batched, total, mode="edge")
    run = _compiled(fn, tuple(sorted(static.items())), mesh)
    out = run(batched, replicated)
    return jax.tree.map(lambda a: a[:b], out) if total != b else out


@functools.cache  # one entry per (kernel, static sizes): SGM uses hundreds
def _compiled(fn, static_items, mesh):
    static = dict(static_items)

    def body(batched, replicated):
        return fn(*batched, *replicated, **static)

    def run(batched, replicated):
        spec_b = jax.tree.map(lambda _: PartitionSpec(BATCH_AXIS), batched)
        spec_r = jax.tree.map(lambda _: PartitionSpec(), replicated)
        return jax.shard_map(body, mesh=mesh, in_specs=(spec_b, spec_r),
                             out_specs=PartitionSpec(BATCH_AXIS), check_vma=False)(batched, replicated)

    name = storable_name(fn)
    if name is not None:  # the closure fixes the statics and the mesh: part of the program's name
        name += f" on devices {tuple(d.id for d in mesh.devices.flat)} {static_items!r}"
    return stored(jax.jit(run), name)
