"""``mbaps://`` buses in the poller's configuration (#31.1): ``tls_cert``, ``tls_key``
and ``tls_ca`` (relative to the configuration file) make the bus's client context;
``pyrtu poll --config`` polls a device behind pyrtu's own TLS listener with them.
Errors name file:line: key and exit 2: a key missing on an mbaps:// bus, keys on
another port, a file that does not exist or does not hold a certificate (or the
certificate's key).  The certificates are made by tests/tls_certs.py."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import pyrtu
from tls_certs import Pki, make_pki

from pyrtu import DataStore
from pyrtu.poller import ConfigError, load_config, parse_config
from pyrtu.poller.masters import open_async_master, open_thread_master
from pyrtu.poller.plan import Wire
from pyrtu.security.tls import TlsListen, server_context
from pyrtu.tcp.server import TcpServer

BUS = """[[bus]]
name = "drive"
port = "{port}"
timeout = 5.0
{tls}
[[point]]
name = "drive.speed"
bus = "drive"
slave = 1
table = "holding"
address = 2
"""


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("pki"))


@pytest.fixture
def tls_server(pki: Pki) -> Iterator[tuple[DataStore, int]]:
    """pyrtu's TLS listener (no policy: every client with a certificate of the CA)."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    store = DataStore()
    store.holding_registers.add_range(0, [1000 + n for n in range(10)])
    srv = TcpServer.for_store(1, store)
    tls = TlsListen("127.0.0.1", 0, server_context(pki.server.cert, pki.server.key, pki.ca.path))
    asyncio.run_coroutine_threadsafe(srv.start("127.0.0.1", 0, tls=tls), loop).result(30)
    assert srv.tls_address is not None
    yield store, srv.tls_address[1]
    asyncio.run_coroutine_threadsafe(srv.close(), loop).result(30)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    loop.close()


def tls_keys(cert: object, key: object, ca: object) -> str:
    return f'tls_cert = "{cert}"\ntls_key = "{key}"\ntls_ca = "{ca}"\n'


def copy_pki(pki: Pki, folder: Path) -> None:
    """The client's files beside the configuration, as relative names will find them."""
    folder.mkdir(parents=True, exist_ok=True)
    for src, name in ((pki.operator.cert, "client.crt"), (pki.operator.key, "client.key"),
                      (pki.ca.path, "ca.crt")):  # fmt: skip
        (folder / name).write_bytes(src.read_bytes())


def test_poll_config_reads_an_mbaps_device(
    tls_server: tuple[DataStore, int], pki: Pki, tmp_path: Path
) -> None:
    store, port = tls_server
    conf = tmp_path / "plant"
    copy_pki(pki, conf / "pki")
    cfg = conf / "points.toml"
    # relative to the file, not to the working folder (the CLI runs in the repository)
    keys = tls_keys("pki/client.crt", "pki/client.key", "pki/ca.crt")
    cfg.write_text(BUS.format(port=f"mbaps://localhost:{port}", tls=keys))
    r = pyrtu("poll", "--config", cfg, "--duration", "2", "--json", timeout=60)
    assert r.code == 0, (r.out, r.err)
    updates = [d for d in r.json_lines() if d.get("point") == "drive.speed" and "event" not in d]
    assert updates, r.out
    assert updates[0]["value"] == store.holding_registers.get(2) == 1002


@pytest.mark.parametrize("opener", [open_async_master, open_thread_master])
def test_both_masters_open_an_mbaps_bus(
    tls_server: tuple[DataStore, int], pki: Pki, tmp_path: Path, opener: object
) -> None:
    from pyrtu.pdu.requests import BY_FUNCTION

    _, port = tls_server
    copy_pki(pki, tmp_path)
    cfg = tmp_path / "points.toml"
    keys = tls_keys("client.crt", "client.key", "ca.crt")
    cfg.write_text(BUS.format(port=f"mbaps://localhost:{port}", tls=keys))
    bus = load_config(cfg).bus("drive")
    assert bus.tls_files == (str(tmp_path / "client.crt"), str(tmp_path / "client.key"),
                             str(tmp_path / "ca.crt"))  # fmt: skip
    assert bus.wire() == Wire.tcp()  # a socket's wire model, as tcp://

    async def main() -> list[int]:
        master = opener(bus)  # type: ignore[operator]
        try:
            value, _ = await master.transact(BY_FUNCTION[3], 255, 5, 2)
            return list(value)
        finally:
            await master.close()

    assert asyncio.run(main()) == [1005, 1006]  # unit 255: as on tcp://, 0..255 allowed


def where(cfg: Path, key: str) -> str:
    """``file:line`` of ``key`` in the configuration (found in its text here)."""
    lines = cfg.read_text().splitlines()
    return f"{cfg.name}:{next(n for n, text in enumerate(lines, 1) if text.startswith(key))}"


def test_config_errors_name_file_line_key_and_exit_2(pki: Pki, tmp_path: Path) -> None:
    copy_pki(pki, tmp_path)
    (tmp_path / "notes.txt").write_text("not a certificate\n")
    good = ("client.crt", "client.key", "ca.crt")
    cfg = tmp_path / "points.toml"
    mbaps = "mbaps://localhost:802"
    cases = [
        # (port, tls lines, key the error is at (None: the [[bus]] line), words)
        (mbaps, "", None, "bus[0] (\"drive\"): tls_cert: missing (an mbaps:// port needs"),
        (mbaps, 'tls_cert = "client.crt"\ntls_key = "client.key"\n', None, "tls_ca: missing"),
        ("tcp://127.0.0.1:502", 'tls_ca = "ca.crt"\n', "tls_ca",
         "tls_ca: only an mbaps:// port takes TLS files, not 'tcp://127.0.0.1:502'"),
        ("/dev/ttyUSB0", tls_keys(*good), "tls_cert", "tls_cert: only an mbaps:// port"),
        (mbaps, tls_keys("none.crt", *good[1:]), "tls_cert",
         f"tls_cert: {tmp_path / 'none.crt'}: no such file"),
        (mbaps, tls_keys(*good[:2], "missing/ca.crt"), "tls_ca",
         f"tls_ca: {tmp_path / 'missing/ca.crt'}: no such file"),
        (mbaps, tls_keys("notes.txt", *good[1:]), "tls_cert", "tls_cert: "
         f"{tmp_path / 'notes.txt'}: not a certificate (PEM)"),
        (mbaps, tls_keys("client.key", *good[1:]), "tls_cert", "not a certificate (PEM)"),
        (mbaps, tls_keys("client.crt", "ca.crt", "ca.crt"), "tls_key",
         "not a certificate and its key"),
        (mbaps, tls_keys(*good[:2], "notes.txt"), "tls_ca", "not a CA certificate"),
        (mbaps, 'tls_cert = 3\ntls_key = "client.key"\ntls_ca = "ca.crt"\n', "tls_cert",
         "tls_cert: must be a file name, not 3"),
    ]  # fmt: skip
    for port, tls, key, words in cases:
        cfg.write_text(BUS.format(port=port, tls=tls))
        at = where(cfg, key) if key else where(cfg, "[[bus]]")
        with pytest.raises(ConfigError) as info:
            load_config(cfg)
        assert str(info.value).startswith(f"{at}: bus[0]"), (str(info.value), at)
        assert words in str(info.value), (str(info.value), words)
    # as a program: exit 2, one line, no traceback, before any port opens
    cfg.write_text(BUS.format(port=mbaps, tls=tls_keys("none.crt", *good[1:])))
    r = pyrtu("poll", "--config", cfg)
    assert r.code == 2 and r.out == "", (r.out, r.err)
    assert r.err.startswith(f"pyrtu poll: config error: {where(cfg, 'tls_cert')}: bus[0]")
    assert "no such file" in r.err and "Traceback" not in r.err


def test_without_a_base_folder_names_are_the_working_folders(
    pki: Pki, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    copy_pki(pki, tmp_path)
    monkeypatch.chdir(tmp_path)
    keys = tls_keys("client.crt", "client.key", "ca.crt")
    text = BUS.format(port="mbaps://localhost:802", tls=keys)
    bus = parse_config(text, "inline.toml").bus("drive")
    assert bus.tls_files == ("client.crt", "client.key", "ca.crt")
    assert bus.master_options["tls"] is bus.tls and bus.tls is not None
    # the same files: the same bus (a reload that changes nothing reopens nothing)
    assert parse_config(text, "inline.toml").bus("drive") == bus
