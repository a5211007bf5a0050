"""A DataStore's image: its four tables copied into C memory (csrc/rtu_image.h), from
which the C engine of `pyrtu.tcp.server.TcpServer` answers plain reads without
Python (`pyrtu.gateway._engine`).

The store stays the truth: the image is brought up to date by the store's lock
(`pyrtu.protocol.datastore.StoreLock`) when its outermost holder releases it and a
table's ``version`` moved, under the process's image lock (``rtu_images_lock``),
which the engine holds while it reads an image.  So the engine sees every change
made under one hold of the store's lock, or none of it.  A table whose ranges
changed (``add_range``) is laid out again; one whose values changed is copied
whole (the tables of a device are small; a copy of 10,000 registers is some tens
of microseconds).

A range with an ``on_read`` callback is *held*: its reads are Python's (the engine
hands them over), as are every write, every other function and every exception
answer.  C backend on Linux only (`available`).
"""

from __future__ import annotations

from array import array
from typing import Any

from pyrtu.core import _backend
from pyrtu.protocol.datastore import DataStore, Table


def available() -> bool:
    """Whether the C core here has the image lock (and the engine): POSIX I/O."""
    c = _backend.C
    return c is not None and hasattr(c.lib, "rtu_images_lock") and c.lib.rtu_serve_size(1) > 0


def _tables(store: DataStore) -> tuple[Table, Table, Table, Table]:
    # rtu_image's table order: RTU_IMAGE_COILS, _DISCRETE_INPUTS, _HOLDING_REGISTERS,
    # _INPUT_REGISTERS
    return (store.coils, store.discrete_inputs, store.holding_registers, store.input_registers)


class StoreImage:
    """The image of ``store`` (made with its lock held; attached to it as the lock's
    mirror, for the store's life).  ``image``: the ``rtu_image *`` the engine reads.
    Use `of`: one image per store."""

    def __init__(self, store: DataStore) -> None:
        c = _backend.C
        assert c is not None
        self._ffi, self._lib = c.ffi, c.lib
        self._store = store
        self.image: Any = self._ffi.new("rtu_image *")
        tables = _tables(store)
        #: per table: the version copied, the ranges' identity (a layout), the cffi
        #: objects that keep the C memory alive, and the values' views
        self._versions = [-1] * len(tables)
        self._layouts: list[tuple[int, ...]] = [()] * len(tables)
        self._keep: list[Any] = [None] * len(tables)
        self._views: list[list[memoryview]] = [[] for _ in tables]
        with store.lock:
            self._lib.rtu_images_lock()
            try:
                for t, table in enumerate(tables):
                    self._copy(t, table)
            finally:
                self._lib.rtu_images_unlock()
            store.lock.mirror = self

    @classmethod
    def of(cls, store: DataStore) -> StoreImage:
        """``store``'s image, made at the first call."""
        mirror = store.lock.mirror
        if isinstance(mirror, StoreImage):
            return mirror
        if mirror is not None:
            raise RuntimeError(f"the store's lock already keeps {mirror!r} current")
        return cls(store)

    def changed(self) -> bool:
        store = self._store
        v = self._versions
        return (
            store.coils.version != v[0]
            or store.discrete_inputs.version != v[1]
            or store.holding_registers.version != v[2]
            or store.input_registers.version != v[3]
        )

    def update(self) -> None:
        """Copy what changed (the store's lock held: `StoreLock.release`)."""
        lib = self._lib
        lib.rtu_images_lock()
        try:
            for t, table in enumerate(_tables(self._store)):
                if table.version != self._versions[t]:
                    self._copy(t, table)
        finally:
            lib.rtu_images_unlock()

    def _copy(self, t: int, table: Table) -> None:
        """Table ``t``'s values into the image; laid out again if its ranges changed
        (the image lock held)."""
        ranges = table._ranges
        layout = tuple(id(r) for r in ranges)
        if layout != self._layouts[t]:
            ffi = self._ffi
            arr = ffi.new("rtu_image_range[]", max(1, len(ranges)))
            keep: list[Any] = [arr]
            views: list[memoryview] = []
            for i, r in enumerate(ranges):
                count = r.end - r.start
                values = ffi.new("uint16_t[]", count)
                keep.append(values)
                views.append(memoryview(ffi.buffer(values)).cast("H"))
                arr[i].start = r.start
                arr[i].count = count
                arr[i].flags = (
                    self._lib.RTU_IMAGE_HELD if r.on_read is not None else self._lib.RTU_IMAGE_PLAIN
                )
                arr[i].values = values
            self._keep[t] = keep  # (the old memory goes once the image no longer names it)
            self._views[t] = views
            self._layouts[t] = layout
            self.image.ranges[t] = arr
            self.image.nranges[t] = len(ranges)
        for view, r in zip(self._views[t], ranges, strict=True):
            view[:] = array("H", r.values)
        self._versions[t] = table.version

    def __repr__(self) -> str:
        return f"StoreImage({self._store!r})"


__all__ = ["StoreImage", "available"]
