"""Schemas with slots an application fills: a run file's environments are whatever
the application studied says they are.

A generic schema (the run file's `RunSpec`) annotates a field with a *slot* type,
`ApplicationEnvironment` or `ApplicationRandomEnvironments`, alone or inside
``List[...]`` / ``Optional[...]``. `typed_schema` makes, once per schema and set of
types, the same tree of dataclasses with each slot replaced by a concrete dataclass
(the taxi's `Environment`, a cart's own), which the YAML loader, the overlays and the
reference page read; a slot field that is not a list takes its default from the
application (`slot_field`'s ``role``). `untyped` turns what was loaded back into the
generic classes, so that nothing made here at run time travels to a worker."""

import dataclasses as dc
import functools
import typing
from typing import Callable, Dict, List, Optional, Tuple


class ApplicationEnvironment:
    """Stands, in a generic schema, for the application's environment dataclass (it
    has a ``name`` and ``validate()``)."""


class ApplicationRandomEnvironments:
    """Stands, in a generic schema, for the application's family of random
    environments (``count``, ``seed``, ``prefix``; ``validate(where)`` and
    ``environments()``)."""


#: The metadata key of a slot field's role (what its default is for).
ROLE = "reachwatch.application_role"


def slot_field(role: str, default_factory: Callable, **kwargs):
    """A dataclass field of a slot type whose default is the application's for
    ``role`` (``default_factory`` gives the default application's, for a schema built
    in code); a list of slots takes ``default_factory=list`` and no role."""
    return dc.field(default_factory=default_factory, metadata={ROLE: role}, **kwargs)


def _replace(annotation, types: Dict[type, type]):
    """``annotation`` with each slot in it replaced by its type in ``types``."""
    if annotation in types:
        return types[annotation]
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (list, List) and args:
        return List[_replace(args[0], types)]
    if origin is typing.Union:
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1 and len(args) == 2:
            return Optional[_replace(inner[0], types)]
    if origin in (dict, Dict) and args:
        return Dict[args[0], _replace(args[1], types)]
    return annotation


def _dataclasses_in(annotation) -> List[type]:
    if dc.is_dataclass(annotation):
        return [annotation]
    return [c for a in typing.get_args(annotation) for c in _dataclasses_in(a)]


def typed_schema(schema: type, types: Tuple[Tuple[type, type], ...],
                 defaults: Callable[[type, str], Callable]) -> type:
    """``schema`` with every slot in its tree of dataclasses replaced: ``types`` pairs
    each slot with its dataclass, ``defaults(slot, role)`` is the factory of a slot
    field's default. A dataclass with no slot below it is kept as it is; one with a
    slot becomes a subclass of the same name, fields and methods (memoised: the same
    arguments give the same class)."""
    return _typed(schema, tuple(types), defaults)


@functools.lru_cache(maxsize=None)
def _typed(schema, types, defaults):
    mapping = dict(types)
    hints = typing.get_type_hints(schema)
    changed = []
    for field in dc.fields(schema):
        annotation = hints[field.name]
        new = _replace(annotation, mapping)
        for inner in _dataclasses_in(annotation):
            typed = _typed(inner, types, defaults)
            if typed is not inner:
                new = _replace(new, {inner: typed})
        if new == annotation:
            continue
        if annotation in mapping:                       # a slot itself: its default too
            factory = defaults(annotation, field.metadata[ROLE])
        elif dc.is_dataclass(annotation):
            if field.default_factory is not annotation:
                raise TypeError(f"{schema.__name__}.{field.name}: a field holding slots "
                                f"takes its class as its default factory")
            factory = new
        else:
            factory = field.default_factory            # a list: list
        default = (dict(default=field.default) if field.default is not dc.MISSING
                   else dict(default_factory=factory))
        changed.append((field.name, new, dc.field(metadata=field.metadata, **default)))
    if not changed:
        return schema
    typed = dc.make_dataclass(schema.__name__, changed, bases=(schema,),
                              namespace={"__doc__": schema.__doc__},
                              module=schema.__module__)
    typed.__untyped__ = schema
    return typed


def untyped(value):
    """``value`` (what a typed schema loaded) with every instance of a typed class
    turned into one of its generic class, the same fields (slot values are kept: they
    are the application's own dataclasses)."""
    if isinstance(value, list):
        return [untyped(v) for v in value]
    cls = type(value)
    if dc.is_dataclass(value) and not isinstance(value, type):
        fields = {f.name: untyped(getattr(value, f.name)) for f in dc.fields(value)}
        base = cls.__dict__.get("__untyped__", cls)
        if base is cls:
            for name, item in fields.items():
                if item is not getattr(value, name):
                    setattr(value, name, item)
            return value
        return base(**fields)
    return value
