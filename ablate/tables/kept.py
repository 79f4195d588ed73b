"""What a table's runs carry beside them in ``runs.attrs`` (the counts and detections per test frame, the tuning
trials), shared rather than copied. pandas deep-copies a frame's ``attrs`` into every frame and series derived from
it (a column read, a selection); with a table's counts per frame there (thousands of rows, a thousand columns), each
column read of its runs took 0.2 s, most of a report's time."""

from __future__ import annotations

from typing import Any

import pandas as pd


class Kept:
    """A value in ``attrs`` that every derived frame shares: its copy is itself (read it, never change it)."""

    __slots__ = ("value",)

    def __init__(self, value: Any) -> None:
        self.value = value

    def __copy__(self) -> Kept:
        return self

    def __deepcopy__(self, memo: dict) -> Kept:
        return self


def keep(runs: pd.DataFrame, key: str, value: Any) -> None:
    """Put ``value`` beside ``runs`` as ``key``, shared by every frame derived from them."""
    runs.attrs[key] = Kept(value)


def kept(runs: pd.DataFrame, key: str) -> Any:
    """What :func:`keep` put beside ``runs`` as ``key`` (or a value put in ``attrs`` as it is); None where none."""
    value = runs.attrs.get(key)
    return value.value if isinstance(value, Kept) else value
