"""An attribute of a driver that is an attribute of one of its parts: the slave's
``busy`` and ``listen_only`` are its serial-line state's (`pyrtu.protocol.diagnostics.LineState`),
a TCP client's ``timeout`` and ``last_answer_time`` its protocol's.  `Forward` reads
it (assigning raises AttributeError, as for a property without a setter);
`Settable` also writes it, through a check (ValueError/TypeError before anything
changes)."""

from __future__ import annotations

from collections.abc import Callable
from operator import attrgetter
from typing import Any, Generic, NoReturn, TypeVar, overload

T = TypeVar("T")


class Forward(Generic[T]):
    """``owner.name`` is ``owner.<part>.<attr>`` (``attr``: the name by default)."""

    def __init__(self, part: str, attr: str | None = None, doc: str | None = None) -> None:
        self._part = attrgetter(part)
        self._attr = attr
        self.name = attr or ""
        self.__doc__ = doc

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name
        if self._attr is None:
            self._attr = name

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> Forward[T]: ...
    @overload
    def __get__(self, obj: object, owner: type | None = None) -> T: ...
    def __get__(self, obj: object, owner: type | None = None) -> Forward[T] | T:
        if obj is None:
            return self
        value: T = getattr(self._part(obj), self._attr or self.name)
        return value

    def __set__(self, obj: object, value: NoReturn) -> None:
        raise AttributeError(
            f"property {self.name!r} of {type(obj).__name__!r} object has no setter"
        )


class Settable(Forward[T]):
    """A `Forward` that is also written: ``owner.name = v`` sets the part's attribute
    to ``check(v)``."""

    def __init__(
        self, part: str, check: Callable[[Any], T], attr: str | None = None, doc: str | None = None
    ) -> None:
        super().__init__(part, attr, doc)
        self._check = check

    def __set__(self, obj: object, value: T) -> None:
        setattr(self._part(obj), self._attr or self.name, self._check(value))


__all__ = ["Forward", "Settable"]
