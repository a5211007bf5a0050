"""Drop-in adapters: pyrtu's C CRC and framer inside other Modbus libraries.

One module per library, each imported only when asked for (this package imports
none of them)::

    import pyrtu.compat.pymodbus; pyrtu.compat.pymodbus.install()
    import pyrtu.compat.minimalmodbus; pyrtu.compat.minimalmodbus.install()
    import pyrtu.compat.umodbus; pyrtu.compat.umodbus.install()
    import pyrtu.compat.modbus_tk; pyrtu.compat.modbus_tk.install()

Each has ``install()``, ``uninstall()``, ``installed()`` and ``patched()`` (a context
manager), and refuses a library version it is not tested with
(`UnsupportedVersionError`, naming the installed version).  See docs/COMPAT.md.
"""

from __future__ import annotations

from ._guard import PYMODBUS_RELEASES, TESTED, UnsupportedVersionError

__all__ = ["PYMODBUS_RELEASES", "TESTED", "UnsupportedVersionError"]
