"""Bounds of a schema's numbers, declared once beside each field.

A field declared with `bounded` carries its `Bound` in the dataclass field's metadata;
`check_bounds` refuses a value outside it, and the run-file reference
(`reachwatch.pipeline.reference`) prints it, so what the reference says and what is
enforced are the same declaration::

    @dc.dataclass
    class RefineSpec:
        levels: int = bounded(0, 0, 5, whole=True)
        band: float = bounded(2.0, 0.0, 1000.0, unit="m")

    RefineSpec(levels=9).validate()   # ValueError: refine.levels must be a whole number
                                      # in [0, 5], got 9

Relations between fields (``near < far``) stay in the schema's own ``validate``; a
bound's ``note`` says so in the reference."""

import dataclasses as dc
import math
import numbers
from typing import Optional, Tuple

from .checks import short

#: The largest whole number a field may hold, and the range of seeds.
MAX_INT = 2 ** 31 - 1


@dc.dataclass(frozen=True)
class Bound:
    """``low`` <= value <= ``high`` (``None``: unbounded on that side; ``low_open`` /
    ``high_open``: the end itself is refused); ``whole``: an int; ``unit``: what the
    number counts, for messages. For a list field, ``each`` bounds every item and
    ``items`` is ``(least, most)`` items (``most`` None: no limit). ``note``: a relation
    to other fields that the schema's ``validate`` checks, shown in the reference."""
    low: Optional[float] = None
    high: Optional[float] = None
    low_open: bool = False
    high_open: bool = False
    whole: bool = False
    unit: str = ""
    each: bool = False
    items: Optional[Tuple[int, Optional[int]]] = None
    note: str = ""

    @property
    def has_range(self) -> bool:
        return self.low is not None or self.high is not None

    def interval(self) -> str:
        """``[0, 1]``, ``(0, 100]``, ``>= 0``, ``> 0``, ``<= 5`` (empty: any value)."""
        if self.low is not None and self.high is not None:
            return (f"{'(' if self.low_open else '['}{_text(self.low)}, {_text(self.high)}"
                    f"{')' if self.high_open else ']'}")
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {_text(self.low)}"
        if self.high is not None:
            return f"{'<' if self.high_open else '<='} {_text(self.high)}"
        return ""

    def number_text(self) -> str:
        """``a whole number in [0, 5]``, ``a finite number >= 0 m``."""
        kind = "a whole number" if self.whole else "a finite number"
        interval = self.interval()
        if not interval:
            return kind
        joined = f"{kind} in {interval}" if interval[0] in "[(" else f"{kind} {interval}"
        return f"{joined} {self.unit}" if self.unit else joined

    def items_text(self) -> str:
        """``3 items``, ``at most 20 items``, ``1 to 8 items`` (empty: any count)."""
        if self.items is None:
            return ""
        least, most = self.items
        if most is None:
            return f"at least {least} items"
        if least == most:
            return f"{least} items"
        return f"at most {most} items" if least == 0 else f"{least} to {most} items"

    def text(self) -> str:
        """The bound as the reference prints it: ``[0, 1] m``, ``3 items, each in [3,
        401]``, with the note after a semicolon."""
        value = self.interval() + (f" {self.unit}" if self.unit and self.interval() else "")
        if self.each and value:
            value = f"each {'in ' if value[0] in '[(' else ''}{value}"
        parts = [p for p in (self.items_text(), value) if p]
        text = ", ".join(parts)
        return f"{text}; {self.note}" if self.note and text else (text or self.note)

    def admits(self, value) -> bool:
        """Whether one number lies inside (its type included: an int for ``whole``)."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return False
        if self.whole and not isinstance(value, numbers.Integral):
            return False
        if not math.isfinite(value):
            return False
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            return False
        if self.high is not None and (value > self.high or (self.high_open and value == self.high)):
            return False
        return True

    def check(self, key: str, value):
        """``value`` if it lies inside; else a one-line ValueError naming ``key``."""
        if value is None:
            return value
        if self.each or self.items is not None:
            if not isinstance(value, (list, tuple)):
                raise ValueError(f"{key} must be a list, got {short(value)}")
            least, most = self.items or (0, None)
            if len(value) < least or (most is not None and len(value) > most):
                raise ValueError(f"{key} must list {self.items_text()}, got {len(value)}: "
                                 f"{short(value)}")
            if self.each and self.has_range:
                for i, item in enumerate(value):
                    if not self.admits(item):
                        raise ValueError(f"{key}[{i}] must be {self.number_text()}, got "
                                         f"{short(item)}")
            return value
        if not self.admits(value):
            raise ValueError(f"{key} must be {self.number_text()}, got {short(value)}")
        return value


def _text(number) -> str:
    """A bound's number as written: ``2147483647``, ``0.0003``, ``-360``."""
    if float(number).is_integer():
        return str(int(number))
    return f"{number:g}"


def bounded(default=dc.MISSING, low=None, high=None, *, default_factory=dc.MISSING, **bound):
    """A dataclass field with ``default`` (or ``default_factory``) whose `Bound` is
    ``Bound(low, high, **bound)``."""
    return dc.field(default=default, default_factory=default_factory,
                    metadata={"bound": Bound(low, high, **bound)})


def bounded_as(default, cls, name: str, *, default_factory=None, **changes):
    """A field with ``default`` (or ``default_factory``, for a list) bounded as the
    field ``name`` of the dataclass ``cls`` (with ``changes`` to its `Bound`, e.g. a
    ``note``): one quantity, one declaration."""
    metadata = {"bound": dc.replace(bounds(cls)[name], **changes)}
    if default_factory is not None:
        return dc.field(default_factory=default_factory, metadata=metadata)
    return dc.field(default=default, metadata=metadata)


def seed_field(default: int = 0):
    """A seed: a whole number in [0, `MAX_INT`]."""
    return bounded(default, 0, MAX_INT, whole=True)


def bound_of(field: dc.Field) -> Optional[Bound]:
    """The `Bound` declared for a dataclass field, or None."""
    return field.metadata.get("bound")


def bounds(cls_or_obj):
    """``{name: Bound}`` of the bounded fields of a dataclass, in field order."""
    return {f.name: bound_of(f) for f in dc.fields(cls_or_obj) if bound_of(f) is not None}


def check_bounds(obj, prefix: str = ""):
    """Check every bounded field of the dataclass instance ``obj``; a ValueError naming
    the first one outside as ``prefix + name`` (e.g. ``prefix="refine."``). Returns
    ``obj``."""
    for name, bound in bounds(obj).items():
        bound.check(f"{prefix}{name}", getattr(obj, name))
    return obj
