"""The transports in one table (`pyrtu.drivers.links.TRANSPORTS`): every scheme pyrtu
opens has its row, each row's link classes exist and open, and the masters pick their
link from the table alone (no branch on the scheme in `Master`/`AsyncMaster`)."""

from __future__ import annotations

import ast
import inspect

from pyrtu.drivers import aio, master
from pyrtu.drivers._portname import PYRTU_SCHEMES
from pyrtu.drivers.links import TRANSPORTS, transport_of


def test_every_scheme_has_one_row_and_its_links_open() -> None:
    assert set(TRANSPORTS) == {None, *PYRTU_SCHEMES}
    for scheme, row in TRANSPORTS.items():
        assert row.scheme == scheme
        for asyncio in (False, True):
            link = row.link_class(asyncio)
            assert callable(getattr(link, "open", None)), (scheme, link)
    assert transport_of("/dev/ttyUSB0") is TRANSPORTS[None]
    assert transport_of("socket://h:1") is TRANSPORTS[None]  # pyserial's URLs: a serial line
    assert transport_of("MBAPS://h") is TRANSPORTS["mbaps"] and TRANSPORTS["mbaps"].tls


def test_the_masters_hold_no_branch_on_the_scheme() -> None:
    for module in (master, aio):
        tree = ast.parse(inspect.getsource(module))
        names = {
            node.id
            for node in ast.walk(tree)
            if isinstance(node, ast.Name) and ("SCHEME" in node.id or node.id == "scheme")
        }
        assert not names, f"{module.__name__} branches on the scheme: {sorted(names)}"
