"""The transports in one table (`pyrtu.drivers.links.TRANSPORTS`): every scheme pyrtu
opens has its row, each row's link classes exist and open, and the masters pick their
link from the table alone (no branch on the scheme in `Master`/`AsyncMaster`)."""

from __future__ import annotations

import ast
import inspect
import re

import pytest

from pyrtu.drivers import aio, master
from pyrtu.drivers._portname import PYRTU_SCHEMES
from pyrtu.drivers.links import TRANSPORTS, transport_of
from pyrtu.poller import config as poller_config


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
    udp = transport_of("udp://plc")
    assert udp.scheme == "udp" and udp.mbap and udp.pipelines and not udp.tls
    assert [s for s, row in TRANSPORTS.items() if row.mbap] == ["tcp", "mbaps", "udp"]


def test_each_row_checks_its_urls_before_anything_opens() -> None:
    for url in ("tcp://:502", "udp://plc:99999", "rtu+tcp://", "mbaps://h/x"):
        with pytest.raises(ValueError, match=re.escape(url)):
            transport_of(url).check_port(url)
    for url in ("tcp://plc", "udp://[::1]:5020", "rtu+tcp://h:1", "/dev/ttyUSB0", "loop://"):
        transport_of(url).check_port(url)  # (nothing opened: no such host needed)


def test_the_masters_hold_no_branch_on_the_scheme() -> None:
    """Nor does the poller's bus: its unit ids, wire model, ``t35`` and TLS files come
    from the row too, so a new transport needs no change there."""
    for module in (master, aio, poller_config):
        tree = ast.parse(inspect.getsource(module))
        names = {
            node.id
            for node in ast.walk(tree)
            if isinstance(node, ast.Name) and ("SCHEME" in node.id or node.id == "scheme")
        }
        assert not names, f"{module.__name__} branches on the scheme: {sorted(names)}"
