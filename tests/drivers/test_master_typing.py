"""The request methods are generated from one table, yet users' ``mypy --strict``
still sees their precise types (issue 18, item 4)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

USER_CODE = """
import pyrtu
from pyrtu.drivers.aio import AsyncMaster


async def main() -> None:
    async with AsyncMaster("tcp://127.0.0.1:502") as m:
        reveal_type(await m.read_holding_registers(1, 0, 2))
        reveal_type(await m.read_device_identification(1))
        reveal_type(await m.get_comm_event_counter(1))
        reveal_type(m.line)


with pyrtu.Master("/dev/ttyUSB0") as bus:
    reveal_type(bus.read_coils(1, 0, 8))
pyrtu.Slave("/dev/ttyUSB1", baudrate="fast")
"""


def test_users_mypy_sees_the_methods_types(tmp_path: Path) -> None:
    user = tmp_path / "user.py"
    user.write_text(USER_CODE)
    out = subprocess.run(
        [sys.executable, "-m", "mypy", "--strict", "--cache-dir", str(tmp_path / "cache"),
         str(user)],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    revealed = [line.split("Revealed type is ")[1] for line in out.stdout.splitlines()
                if "Revealed type is" in line]  # fmt: skip
    assert revealed == [
        '"list[int]"',
        '"dict[int, bytes]"',
        '"tuple[int, int]"',
        '"pyrtu.core.line.LineConfig"',
        '"list[bool]"',
    ], out.stdout
    # the slave's line keywords are typed too (one TypedDict, pyrtu.core.line.LineKeywords)
    assert 'Argument "baudrate" to "Slave" has incompatible type "str"' in out.stdout
