"""Naming the field whose converter is running, for error messages (no other imports: every
module that defines fields may use it)."""

from __future__ import annotations

import dataclasses
import sys

__all__ = ["converter_field"]


def converter_field(max_depth: int = 8) -> tuple[str | None, str | None]:
    """``(class name, field name)`` of the ``eqx.field(converter=...)`` being run, or ``None``s.

    Equinox calls a field's converter with the value alone; to name the argument in an error the
    converter reads the field from the caller's frame (equinox's ``Module.__call__`` holds it as
    the local ``f``, a ``dataclasses.Field``). Best effort: ``(None, None)`` if not found.
    """
    try:
        frame = sys._getframe(2)
    except ValueError:  # pragma: no cover
        return None, None
    for _ in range(max_depth):
        if frame is None:
            break
        field = frame.f_locals.get("f")
        if isinstance(field, dataclasses.Field):
            cls = frame.f_locals.get("cls")
            return (getattr(cls, "__name__", None), field.name)
        frame = frame.f_back
    return None, None
