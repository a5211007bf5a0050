"""`import pyrtu` where the POSIX terminal modules do not exist (as on Windows).

A subprocess installs a meta-path hook that refuses ``termios``, ``fcntl``, ``tty``,
``pty`` (and the other POSIX-only modules below) and removes ``select.poll``, as
Windows's ``select`` has none; then it imports pyrtu and uses the layers that must
work everywhere: CRC, LRC, the framers, ``parse_stream``, the PDU layer, the data
helpers, capture files, and a serial port through pyserial's generic path
(``loop://``, pyserial's own loopback, needs no operating-system port).
pyserial itself is imported before the hook: it chooses its platform module by
``os.name`` (on Windows its win32 one, which cannot load here).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pyrtu

ROOT = str(Path(pyrtu.__file__).resolve().parent.parent)  # this pyrtu (the ASan run's copy too)

BLOCKED = ("termios", "fcntl", "tty", "pty", "resource", "grp", "pwd")

SCRIPT = r"""
import importlib.abc, select, sys

BLOCKED = set(sys.argv[1].split(","))
loaded = BLOCKED & set(sys.modules)
assert not loaded, f"already imported at start-up: {loaded}"


class Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


# pyserial picks its platform module itself (serialwin32 on Windows, which cannot
# load here): import it first, then take the POSIX modules away from everyone else.
import serial, serial.rs485

for name in BLOCKED:
    sys.modules.pop(name, None)
sys.meta_path.insert(0, Refuse())
del select.poll
sys.path.insert(0, sys.argv[2])

import pyrtu
import pyrtu.cli
from pyrtu import data, pdu
from pyrtu.core.ascii import AsciiFramer
from pyrtu.drivers.port import open_port
from pyrtu.vbus import read_capture

assert pyrtu.BACKEND == sys.argv[3], pyrtu.BACKEND
assert pyrtu.crc16(b"123456789") == 0x4B37
frame = pyrtu.add_crc(b"\x01" + pdu.read_request(3, 0x6B, 3))
assert frame == bytes.fromhex("0103006b00037417"), frame.hex()
assert pyrtu.check_crc(frame)
assert pyrtu.lrc(bytes.fromhex("110300 6B0003")) == 0x7E
message = bytes.fromhex("1103006b0003")
assert pyrtu.decode_ascii(pyrtu.encode_ascii(message)) == message

framer = pyrtu.Framer("slave", baudrate=19200)
framer.receive_data(frame, 1.0)
framer.handle_timer(2.0)
event = framer.next_event()
assert event is not None and event.error is None and event.adu == frame, event
frames = pyrtu.parse_stream(frame + frame, "slave")
assert [f.adu for f in frames] == [frame, frame], frames

ascii_framer = AsciiFramer("slave")
ascii_framer.receive_data(pyrtu.encode_ascii(message), 1.0)
event = ascii_framer.next_event()
assert event is not None and event.error is None and event.message == message, event

answer = bytes.fromhex("03" "06" "022b" "0000" "0064")
assert pdu.parse_registers(answer, 3) == [0x022B, 0, 0x64]
assert data.decode_float32(data.encode_float32(1.5)) == 1.5

try:
    from pyrtu.vbus import VirtualBus
except ImportError as exc:
    assert "POSIX pseudo-terminals" in str(exc), exc
else:
    raise AssertionError("VirtualBus imported without termios")

port = open_port("loop://", baudrate=19200, parity="N")
assert port.fd is None  # pyserial's generic path
port.write(frame)
assert port.read(0.5) == frame
port.close()

leaked = BLOCKED & set(sys.modules)
assert not leaked, leaked
print("ok", pyrtu.BACKEND)
"""


def test_import_without_posix_terminal_modules(backend: ModuleType) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYRTU_")}
    if backend.BACKEND == "python":
        env["PYRTU_PURE"] = "1"
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, ",".join(BLOCKED), ROOT, backend.BACKEND],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["ok", backend.BACKEND]
