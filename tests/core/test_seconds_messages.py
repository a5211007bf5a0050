"""Every duration argument is checked by one function (`pyrtu.core.timing.check_seconds`)
and so says the same words, naming the argument in the caller's terms: the masters,
the slaves, the gateway's limits, the reconnect schedule, the bridge's TOML keys.
(Before, five helpers said "must be positive", "must be finite and >= 0 seconds",
"must be a finite number of seconds > 0" or "must be a number of seconds".)"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from ptylink import PtyLink

from pyrtu import Master, Slave
from pyrtu.bridge.config import MqttConfig
from pyrtu.core.timing import check_seconds, positive_seconds
from pyrtu.drivers.reconnect import Backoff
from pyrtu.gateway import GatewayLimits

POSITIVE = "must be a positive number of seconds, not "
NON_NEGATIVE = "must be a non-negative number of seconds, not "
MISSING = "/dev/pyrtu-no-such-port"  # refused arguments are reported before it is opened

CASES: list[tuple[Callable[[], object], type[Exception], str]] = [
    (lambda: Master(MISSING, timeout=0), ValueError, "timeout " + POSITIVE + "0"),
    (lambda: Master(MISSING, timeout="1"), ValueError, "timeout " + POSITIVE + "'1'"),
    (
        lambda: Master(MISSING, broadcast_delay=math.nan),
        ValueError,
        "broadcast_delay " + NON_NEGATIVE + "nan",
    ),
    (lambda: Backoff(initial=0), ValueError, "initial " + POSITIVE + "0"),
    (lambda: Backoff(maximum=math.inf), ValueError, "maximum " + POSITIVE + "inf"),
    (lambda: Backoff(initial=True), TypeError, "initial " + POSITIVE + "True"),
    (lambda: GatewayLimits(close_grace=-1), ValueError, "close_grace " + NON_NEGATIVE + "-1"),
    (lambda: GatewayLimits(idle_timeout="5"), TypeError, "idle_timeout " + NON_NEGATIVE + "'5'"),
    (
        lambda: MqttConfig(url="mqtt://localhost", fsync_interval=-1.0),
        ValueError,
        "fsync_interval: " + NON_NEGATIVE + "-1.0",
    ),
    (
        lambda: MqttConfig(url="mqtt://localhost", command_expiry=0),
        ValueError,
        "command_expiry: " + POSITIVE + "0",
    ),
    (lambda: positive_seconds(math.inf, "inter_char"), ValueError, "inter_char " + POSITIVE),
]


@pytest.mark.parametrize(("make", "error", "message"), CASES)
def test_a_bad_duration_names_the_argument(
    make: Callable[[], object], error: type[Exception], message: str
) -> None:
    with pytest.raises(error) as info:
        make()
    assert str(info.value).startswith(message), str(info.value)


def test_the_slave_says_the_same() -> None:
    with PtyLink() as link:
        for delay, shown in ((-1, "-1"), (math.inf, "inf"), (True, "True")):
            with pytest.raises(ValueError, match=f"^response_delay {NON_NEGATIVE}{shown}$"):
                Slave(link.path_b, parity="N", response_delay=delay)


def test_check_seconds_bounds() -> None:
    assert check_seconds("t", 0) == 0.0 and isinstance(check_seconds("t", 2), float)
    assert check_seconds("t", 1e-9, True) == 1e-9
    for bad in (-1e-9, math.inf, -math.inf, math.nan):
        with pytest.raises(ValueError, match="^t " + NON_NEGATIVE):
            check_seconds("t", bad)
    with pytest.raises(ValueError, match="^t " + POSITIVE + "0$"):
        check_seconds("t", 0, True)
    for wrong in (None, "1", b"1", [1], False):
        with pytest.raises(TypeError, match="^t " + NON_NEGATIVE) as info:
            check_seconds("t", wrong)
        assert isinstance(info.value, ValueError)  # what callers caught before: still caught
