"""How the commands word a first-use estimate (the line that says what will be built and how long)."""

from __future__ import annotations


def about(seconds: float) -> str:
    """``seconds`` in words: "under a minute", "about 1 min", "about 12 min"."""
    if seconds < 45:
        return "under a minute"
    return f"about {max(1, round(seconds / 60))} min"
