"""One registry for each sort of named kind (spaces, fitnesses, agents, engines, tasks): entries
known by name, registered, got back with an error that names the known ones, and listed."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Generic, TypeVar

T = TypeVar("T")
_RAISE = object()


class Registry(Generic[T]):
    """The entries of one sort, by name.

    Args:
      what: the sort's name in messages ("space", "physics").
      entries: the first entries.
      plural: its plural ("spaces" unless given).
      sort: `list` in sorted order (else in the order registered).
    Entries are known by their `name` attribute.
    """

    def __init__(self, what: str, entries: Iterable[T] = (), *, plural: str = "",
                 sort: bool = False):
        self.what, self.plural, self.sort = what, plural or what + "s", sort
        self._entries: dict[str, T] = {}
        self.register(*entries)

    def register(self, *entries: T) -> None:
        """Makes `entries` known by their names (a name registered again is replaced)."""
        self._entries.update({e.name: e for e in entries})

    def get(self, name: str, default=_RAISE) -> T:
        """The entry registered as `name`; a ValueError naming the known ones where there is
        none, or `default` if given (as a dict's, which pytest's monkeypatch.setitem calls)."""
        if name in self._entries:
            return self._entries[name]
        if default is not _RAISE:
            return default
        raise ValueError(f"unknown {self.what} {name!r}; known {self.plural}: "
                         f"{', '.join(self.list())}")

    def list(self) -> list[str]:
        """The names registered, sorted or in the order registered."""
        return sorted(self._entries) if self.sort else list(self._entries)

    def __contains__(self, name: str) -> bool:
        return name in self._entries

    # As a dict, for pytest's monkeypatch.setitem (a test's engine in place of a registered one).
    def __getitem__(self, name: str) -> T:
        return self.get(name)

    def __setitem__(self, name: str, entry: T) -> None:
        self._entries[name] = entry

    def __delitem__(self, name: str) -> None:
        del self._entries[name]
