"""Device copies (and other derived tables) of long-lived objects, held by an explicit cache.

A sharded call whose replicated arguments (a catalog's star tables, a database, network weights)
sit on one device copies them to the others on every call. Tables that belong to a long-lived owner
are therefore placed on every device once and kept in a :class:`DeviceCache`, keyed by the owner,
the table's name and the mesh. An entry lives as long as its owner: it is dropped when the owner is
garbage-collected (the owner is referenced weakly, never modified).
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any

from jstarid.runtime.devices import batch_mesh, replicate

__all__ = ["DeviceCache", "device_cache", "on_every_device"]


class DeviceCache:
    """Replicated device copies of owners' tables (see the module docstring).

    Example::

        cache = DeviceCache()
        tables = cache.replicated(database, "weights", lambda: database.weights)
    """

    def __init__(self):
        self._entries: dict[tuple, Any] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def replicated(self, owner, name: str, make: Callable[[], Any], mesh=None):
        """``replicate(make())`` placed once per ``owner``, ``name`` and mesh.

        Args:
            owner: the object the tables belong to (must accept weak references).
            name: which of the owner's tables.
            make: zero-argument function returning the pytree to place (called once).
            mesh: a 1-D mesh (default: :func:`~jstarid.runtime.batch_mesh`).

        Returns:
            The pytree, replicated over the mesh.
        """
        mesh = batch_mesh() if mesh is None else mesh
        key = (id(owner), name, tuple(d.id for d in mesh.devices.flat), mesh.axis_names)
        if key not in self._entries:
            self._entries[key] = replicate(make(), mesh)
            weakref.finalize(owner, self._entries.pop, key, None)
        return self._entries[key]

    def cached(self, owner, name: str, make: Callable[[], Any]):
        """``make()`` computed once per ``owner`` and ``name`` (device arrays on the default device,
        or any table derived from the owner), kept as long as the owner lives."""
        key = (id(owner), name, None, None)
        if key not in self._entries:
            self._entries[key] = make()
            weakref.finalize(owner, self._entries.pop, key, None)
        return self._entries[key]

    def clear(self) -> None:
        """Drop every device copy."""
        self._entries.clear()


device_cache = DeviceCache()
"""The process-wide cache the simulator and the algorithms use."""


def on_every_device(owner, name: str, make: Callable[[], Any], mesh=None):
    """:meth:`DeviceCache.replicated` on the process-wide :data:`device_cache`."""
    return device_cache.replicated(owner, name, make, mesh)
