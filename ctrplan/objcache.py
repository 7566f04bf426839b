"""Caches that live exactly as long as the object they belong to.

A module-level dict keyed by ``id(obj)`` keeps whatever it stores alive for the whole process
(and, when the stored value refers back to ``obj``, ``obj`` too): a service that loads a scene
per request grows without end. Here the cache is a dict stored on the object itself, so it is
freed with it (values that refer back to the object form a reference cycle, which Python's
collector frees). A copy of the object (``copy.copy``, pickling) starts with an empty cache.
Objects that cannot carry one (no ``__dict__``) get ``None``: callers then do not cache.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

_ATTR = "_ctrplan_owned_cache"


class _Owned(dict):
    """The per-object dict; it remembers its owner's id, and copies and pickles empty."""

    __slots__ = ("owner",)

    def __reduce__(self):
        return (_Owned, ())

    def __copy__(self):
        return _Owned()

    def __deepcopy__(self, memo):
        return _Owned()


def owned(obj: Any) -> dict | None:
    """The cache dict of ``obj`` (created on first use), or None when ``obj`` cannot hold one."""
    d = getattr(obj, "__dict__", None)
    if not isinstance(d, dict):
        return None
    cache = d.get(_ATTR)
    if isinstance(cache, _Owned) and getattr(cache, "owner", None) == id(obj):
        return cache
    cache = _Owned()
    cache.owner = id(obj)
    try:
        object.__setattr__(obj, _ATTR, cache)   # frozen dataclasses too
    except (AttributeError, TypeError):
        return None
    return cache


class Bounded(OrderedDict):
    """A dict that keeps only its ``size`` most recently used entries."""

    def __init__(self, size: int):
        super().__init__()
        self.size = int(size)

    def get(self, key, default=None):
        if key in self:
            self.move_to_end(key)
            return self[key]
        return default

    def __setitem__(self, key, value):
        super().__setitem__(key, value)
        self.move_to_end(key)
        while len(self) > self.size:
            self.popitem(last=False)
