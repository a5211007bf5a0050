"""The access policy engine (`pyrtu.security.policy`, sans-I/O) and its file
(`pyrtu.security.policy_file`): decisions at the edges of every range, and every
error naming file:line: key.  Request PDUs are built with `struct` from the
Application Protocol's layouts, not by pyrtu."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from pyrtu.security.policy import Identity, Policy, beyond_loopback, is_read
from pyrtu.security.policy_file import PolicyError, load_policy, parse_policy


def read(function: int, start: int, count: int) -> bytes:
    return struct.pack(">BHH", function, start, count)


def write_registers(start: int, values: list[int]) -> bytes:
    n = len(values)
    return struct.pack(f">BHHB{n}H", 16, start, n, 2 * n, *values)


OPERATOR = Identity("10.0.0.5", 40000, "operator", "CN=panel1")
VIEWER = Identity("10.0.0.6", 40001, "viewer", "CN=screen")
POLICY = """\
# a plant's policy
[[rule]]
name = "operators"
roles = ["operator"]
units = "1-10"
functions = [3, "write_registers", 6]
holding_registers = "100-199,300"

[[rule]]
roles = "viewer"
read_only = true

[[rule]]
name = "office"
clients = ["192.168.1.0/24"]
units = [1]
read_only = true
"""


@pytest.fixture
def policy() -> Policy:
    return parse_policy(POLICY, "plant.toml")


def test_a_role_gets_exactly_its_ranges(policy: Policy) -> None:
    decide = policy.decide
    assert decide(OPERATOR, 1, read(3, 100, 100)).allowed  # 100..199: the whole range
    assert decide(OPERATOR, 10, read(3, 300, 1)).allowed  # the single address, last unit
    edge = decide(OPERATOR, 1, read(3, 199, 2))  # 199..200: one past the range
    assert (edge.allowed, edge.kind) == (False, "address")
    assert decide(OPERATOR, 1, read(3, 99, 1)).kind == "address"  # one before
    assert decide(OPERATOR, 1, write_registers(198, [1, 2])).allowed
    assert decide(OPERATOR, 1, write_registers(199, [1, 2])).kind == "address"
    assert decide(OPERATOR, 11, read(3, 100, 1)).kind == "unit"  # one past units
    assert decide(OPERATOR, 0, read(3, 100, 1)).kind == "unit"
    assert decide(OPERATOR, 1, read(4, 100, 1)).kind == "function"
    assert decide(OPERATOR, 1, struct.pack(">BHH", 6, 150, 7)).allowed
    assert decide(OPERATOR, 1, struct.pack(">BHH", 6, 301, 7)).kind == "address"


def test_read_only_refuses_every_write_and_keeps_reads(policy: Policy) -> None:
    for pdu in (read(1, 0, 8), read(2, 0, 8), read(3, 0, 125), read(4, 0, 1),
                bytes([7]), bytes([11]), bytes([17]), bytes([0x2B, 0x0E, 1, 0]),
                struct.pack(">BHH", 8, 0, 0x1234)):  # fmt: skip
        assert policy.decide(VIEWER, 5, pdu).allowed, pdu.hex()
    for pdu in (struct.pack(">BHH", 5, 0, 0xFF00), struct.pack(">BHH", 6, 0, 1),
                struct.pack(">BHHBB", 15, 0, 1, 1, 1), write_registers(0, [1]),
                struct.pack(">BHHH", 22, 0, 0, 0), struct.pack(">BHHHHBH", 23, 0, 1, 0, 1, 2, 9),
                struct.pack(">BHH", 8, 1, 0), struct.pack(">BHH", 8, 10, 0),  # restart, clear
                bytes([0x2B, 0x0D, 0]), bytes([0x41, 1, 2])):  # fmt: skip
        decision = policy.decide(VIEWER, 5, pdu)
        assert (decision.allowed, decision.kind) == (False, "read_only"), pdu.hex()


def test_clients_by_address_and_no_rule(policy: Policy) -> None:
    assert policy.decide(Identity("192.168.1.255"), 1, read(3, 0, 1)).allowed
    assert policy.decide(Identity("::ffff:192.168.1.7"), 1, read(3, 0, 1)).allowed
    refused = policy.decide(Identity("192.168.2.0"), 1, read(3, 0, 1))
    assert (refused.allowed, refused.kind) == (False, "no_rule")
    unknown = policy.decide(Identity("10.0.0.9", 1, "admin", "CN=x"), 1, read(3, 100, 1))
    assert unknown.kind == "no_rule" and 'role "admin"' in unknown.reason
    no_role = policy.decide(Identity("10.0.0.9", 1, None, "CN=x"), 1, read(3, 100, 1))
    assert no_role.kind == "no_rule" and "without a role" in no_role.reason


def test_a_request_the_rule_cannot_place_is_refused(policy: Policy) -> None:
    assert policy.decide(OPERATOR, 1, bytes([3, 0])).kind == "unplaceable"  # too short
    assert policy.decide(OPERATOR, 1, bytes([3, 0x64, 0, 0])).kind == "unplaceable"


def test_read_only_flag_and_combination(policy: Policy) -> None:
    everyone = Policy.read_only()
    assert everyone.decide(Identity("203.0.113.9"), 7, read(3, 0, 1)).allowed
    assert everyone.decide(Identity("2001:db8::1"), 7, read(3, 0, 1)).allowed
    assert everyone.decide(Identity("203.0.113.9"), 7, write_registers(0, [1])).kind == (
        "read_only"
    )
    both = policy.restricted_to_reads()
    assert both.decide(OPERATOR, 1, read(3, 100, 1)).allowed
    assert both.decide(OPERATOR, 1, write_registers(100, [1])).kind == "read_only"


def test_is_read_of_the_diagnostics_sub_functions() -> None:
    reads = {sub for sub in range(0, 21) if is_read(struct.pack(">BHH", 8, sub, 0))}
    assert reads == {0, 2, 11, 12, 13, 14, 15, 16, 17, 18}  # [AP] 6.8: the reporting ones


def test_loopback() -> None:
    assert not beyond_loopback("127.0.0.1") and not beyond_loopback("127.1.2.3")
    assert not beyond_loopback("::1") and not beyond_loopback("localhost")
    assert beyond_loopback("0.0.0.0") and beyond_loopback("") and beyond_loopback("::")
    assert beyond_loopback("192.168.1.2") and beyond_loopback("plc.example")


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ('[[rule]]\nroles = ["a"]\nunits = "1-300"\n', "p.toml:3: rule[0]: units: "),
        (
            '[[rule]]\nroles = ["a"]\n\n[[rule]]\nclients = ["10.0.0.0/33"]\n',
            "p.toml:5: rule[1]: clients: ",
        ),
        (
            '[[rule]]\nroles = ["a"]\nfunctions = [3, "write_everything"]\n',
            "p.toml:3: rule[0]: functions: ",
        ),
        ('[[rule]]\nroles = ["a"]\nfunctions = [128]\n', "p.toml:3: rule[0]: functions: "),
        ('[[rule]]\nroles = ["a"]\ncoils = "5-2"\n', "p.toml:3: rule[0]: coils: "),
        (
            '[[rule]]\nroles = ["a"]\nholding_registers = "0-65536"\n',
            "p.toml:3: rule[0]: holding_registers: ",
        ),
        ('[[rule]]\nroles = ["a"]\nread_only = "yes"\n', "p.toml:3: rule[0]: read_only: "),
        ('[[rule]]\nroles = ["a"]\nwrite = true\n', "p.toml:3: rule[0]: write: unknown key"),
        ('[[rule]]\nunits = "1"\n', "p.toml:1: rule[0]: a rule needs roles or clients"),
        ("[[rule]]\nroles = []\n", "p.toml:2: rule[0]: roles: "),
        (
            '[[rule]]\nname = "a"\nroles = "x"\n[[rule]]\nname = "a"\nroles = "y"\n',
            "p.toml:5: rule[1]: name: ",
        ),
        ('default = "deny"\n[[rule]]\nroles = "x"\n', "p.toml:1: default: unknown key"),
        ("# nothing\n", "p.toml: rule: no [[rule]]"),
        ('[[rule]]\nroles = "a" "b"\nunits = 1\n', "p.toml:2: not valid TOML"),
        ('[[rule]]\nroles = ["a"\n', "p.toml:2: not valid TOML"),
    ],
)
def test_policy_errors_name_file_line_and_key(text: str, where: str) -> None:
    with pytest.raises(PolicyError) as info:
        parse_policy(text, "p.toml")
    assert str(info.value).startswith(where), str(info.value)


def test_policy_file_missing_or_not_utf8(tmp_path: Path) -> None:
    with pytest.raises(PolicyError, match="no such file"):
        load_policy(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b'[[rule]]\nroles = "\xff"\n')
    with pytest.raises(PolicyError, match="not UTF-8"):
        load_policy(bad)
