"""Named registries with explicit registration.

One :class:`Registry` each for warp models (``warps.py``), objectives (``objectives.py``) and
regularizers (``regularizers.py``). Each of those modules registers its built-in entries by one explicit
call at its bottom; users add their own with :func:`register_warp` and friends.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Generic, TypeVar

T = TypeVar("T")


class Registry(Generic[T]):
    """A name -> entry mapping whose errors list the valid names.

    Parameters
    ----------
    kind : str
        What the entries are ("warp", "objective", ...), used in error messages.
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._entries: dict[str, T] = {}

    def register(self, name: str, entry: T, *, replace: bool = False) -> T:
        """Add ``entry`` under ``name``; refuse to overwrite an existing name unless ``replace``."""
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"{self.kind} name must be an identifier-like string, got {name!r}")
        if name in self._entries and not replace:
            raise ValueError(f"a {self.kind} named {name!r} is already registered")
        self._entries[name] = entry
        return entry

    def get(self, name: str) -> T:
        """The entry called ``name``; ValueError listing the valid names otherwise."""
        if not isinstance(name, str):
            raise TypeError(f"{self.kind} name must be a string, got {type(name).__name__}")
        try:
            return self._entries[name]
        except KeyError:
            raise ValueError(
                f"unknown {self.kind} {name!r}; valid {self.kind}s are: {', '.join(self.names())}"
            ) from None

    def unregister(self, name: str) -> T:
        """Remove the entry called ``name`` and return it; KeyError naming the valid names otherwise."""
        if name not in self._entries:
            raise KeyError(f"no {self.kind} named {name!r}; registered: {', '.join(self.names())}")
        return self._entries.pop(name)

    def names(self) -> list[str]:
        return list(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)
