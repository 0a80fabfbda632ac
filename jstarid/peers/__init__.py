"""Peer solvers: other star identifiers behind jstarid's algorithm contract, each in its own
environment, so that they run on exactly the engine's scenes and are scored by the same rules.

They are not in the default registry (the test suite and the demo never need them); ``--peer NAME``
on ``jstarid demo``/``sweep`` registers one, or ``js.algorithms.register(NAME, PEERS[NAME])``.
"""

PEERS = {"cedar": "jstarid.peers.cedar"}

__all__ = ["PEERS"]
