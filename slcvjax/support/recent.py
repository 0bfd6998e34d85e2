"""The last few results of a function, found again by the identity of its arguments.

A calibration looks at the same objects several times (the same observations padded for each
pass, the same solution's residual table for each check); :class:`Recent` keeps the newest
results so that those repeats cost nothing.  Arguments are matched by identity (``is``), which
holds for the package's immutable pytrees; an optional ``value`` (a small hashable such as a
layout) is matched by equality.  Kept results hold their arguments alive, so an identity is
never reused while it is kept.
"""

from collections.abc import Callable
from typing import Any


class Recent:
    """The ``size`` newest results of ``compute()`` keyed by ``(objects, value)`` (see the module docstring)."""

    def __init__(self, size: int):
        self.size = size
        self._items: list = []  # (objects, value, result), newest first

    def get(self, objects: tuple, value: Any, compute: Callable[[], Any]) -> Any:
        for objs, val, out in self._items:
            if len(objs) == len(objects) and all(a is b for a, b in zip(objs, objects, strict=True)) and val == value:
                return out
        out = compute()
        self._items.insert(0, (objects, value, out))
        del self._items[self.size :]
        return out
