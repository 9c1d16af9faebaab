"""Named registries: what the library chooses by a name in a run file (a fallback's speed
strategy, `systems.switch`; a dataset's label source, `training.labels`) is looked up in
one, so that a new choice is one module that registers it, with no edit elsewhere.

A registry keeps entries (objects with a ``name``) in registration order; `Registry.names`
is a live tuple-like view of their names (what error messages and ``choices`` show).
Registering a name twice is a ValueError; `Registry.registered` registers for a ``with``
block only (tests, experiments). A registered entry's name is all that cache keys and run
files hold of it: an entry whose rule changes should take a new name."""

import collections.abc
import contextlib
import re

#: What a registered name may be: lower case, digits and ``_`` (it is written in run files
#: and on the command line, and joined to other names with ``+``).
NAME = re.compile(r"[a-z][a-z0-9_]*")


class Names(collections.abc.Sequence):
    """The names in a `Registry`, in registration order: a live view that reads, prints
    and compares like the tuple of them."""

    def __init__(self, registry: "Registry"):
        self._registry = registry

    def __getitem__(self, index):
        return tuple(self._registry._entries)[index]

    def __len__(self):
        return len(self._registry._entries)

    def __contains__(self, name):
        return name in self._registry

    def __repr__(self):
        return repr(tuple(self))

    def __eq__(self, other):
        if isinstance(other, (Names, tuple)):
            return tuple(self) == tuple(other)
        return NotImplemented

    __hash__ = None


class Registry:
    """Entries by name; ``what`` names the kind in messages (e.g. ``"speed strategy"``)."""

    def __init__(self, what: str):
        self.what = what
        self._entries = {}
        self.names = Names(self)

    def register(self, entry):
        """Add ``entry`` under ``entry.name`` and return it; a name already registered, or
        not written as `NAME` allows, is a one-line ValueError."""
        name = getattr(entry, "name", None)
        if not isinstance(name, str) or not NAME.fullmatch(name):
            raise ValueError(f"a {self.what}'s name must be lower case letters, digits and "
                             f"'_', starting with a letter, got {name!r}")
        if name in self._entries:
            raise ValueError(f"{self.what} '{name}' is already registered")
        self._entries[name] = entry
        return entry

    def unregister(self, name: str):
        """Remove the entry named ``name`` (a ValueError when there is none)."""
        if name not in self._entries:
            raise ValueError(f"no {self.what} '{name}' is registered")
        del self._entries[name]

    @contextlib.contextmanager
    def registered(self, entry):
        """``entry`` registered for the ``with`` block, and removed after it."""
        self.register(entry)
        try:
            yield entry
        finally:
            self.unregister(entry.name)

    def get(self, name):
        """The entry named ``name``; a KeyError when there is none (callers word their
        own message, naming their field: see `names`)."""
        if name not in self:
            raise KeyError(name)
        return self._entries[name]

    def __contains__(self, name):
        try:
            return name in self._entries
        except TypeError:           # unhashable (a list read from a run file): no name
            return False

    def __iter__(self):
        return iter(tuple(self._entries.values()))

    def __len__(self):
        return len(self._entries)

    def __repr__(self):
        return f"Registry({self.what!r}, {tuple(self.names)})"
