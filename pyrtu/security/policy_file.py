"""The policy file (``--policy FILE``): TOML, one ``[[rule]]`` table per rule::

    [[rule]]
    name = "operators"               # for the log (default: rule[N])
    roles = ["operator"]             # TLS: the role in the client's certificate
    units = "1-10"                   # unit ids (default: all, 0..255)
    functions = [3, 4, 6, 16]        # codes or names (read_holding_registers, ...)
    holding_registers = "0-99"       # tables with address ranges: the tables named
    coils = "0-15,100"               # are the only ones allowed (none named: all)

    [[rule]]
    clients = ["10.0.0.0/8", "::1"]  # plain TCP: client address ranges
    read_only = true

Every error names file:line: rule[N]: key (`PolicyError`, a ValueError).
"""

from __future__ import annotations

import re
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pyrtu.core._text import read_text_file
from pyrtu.core._tomlpos import locate
from pyrtu.pdu.functions import FUNCTION_NAMES

from .policy import TABLES, Network, Policy, Rule, networks, parse_ranges

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

RULE_KEYS = ("name", "roles", "clients", "units", "functions", "read_only", *TABLES)
_CODES = {name: code for code, name in FUNCTION_NAMES.items()}


class PolicyError(ValueError):
    """A policy file that cannot be used (the message names file:line: key)."""


def _strings(value: object) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, list) and value and all(isinstance(v, str) and v for v in value):
        return list(value)
    raise ValueError(f"expected a string or a list of strings, not {value!r}")


def _units(value: object) -> frozenset[int]:
    if isinstance(value, str):
        units = {u for r in parse_ranges(value) for u in r}
    elif isinstance(value, list) and all(
        isinstance(v, int) and not isinstance(v, bool) for v in value
    ):
        units = set(value)
    else:
        raise ValueError(f'expected unit ids like "1-10,255" or [1, 2], not {value!r}')
    if not units or not all(0 <= u <= 255 for u in units):
        raise ValueError(f"expected unit ids 0..255, not {value!r}")
    return frozenset(units)


def _functions(value: object) -> frozenset[int]:
    if not isinstance(value, list) or not value:
        raise ValueError(f"expected a list of function codes or names, not {value!r}")
    codes = set()
    for item in value:
        if isinstance(item, str) and item in _CODES:
            codes.add(_CODES[item])
        elif isinstance(item, int) and not isinstance(item, bool) and 1 <= item <= 127:
            codes.add(item)
        else:
            names = ", ".join(sorted(_CODES))
            raise ValueError(f"expected a function code 1..127 or one of {names}, not {item!r}")
    return frozenset(codes)


def _addresses(value: object) -> tuple[range, ...]:
    if isinstance(value, str):
        return parse_ranges(value)
    raise ValueError(f'expected address ranges like "0-99,200", not {value!r}')


def _rule(index: int, table: Mapping[str, Any], fail: Any) -> Rule:
    name = table.get("name", f"rule[{index}]")
    if not isinstance(name, str) or not name:
        raise fail(index, "name", f"expected a non-empty string, not {name!r}")
    for key in table:
        if key not in RULE_KEYS:
            raise fail(index, key, f"unknown key (the keys: {', '.join(RULE_KEYS)})")
    if "roles" not in table and "clients" not in table:
        raise fail(index, None, "a rule needs roles or clients (whom it is for)")
    kw: dict[str, Any] = {}
    try:
        key = "roles"
        if key in table:
            kw["roles"] = frozenset(_strings(table[key]))
        key = "clients"
        if key in table:
            found: tuple[Network, ...] = networks(_strings(table[key]))
            kw["clients"] = found
        key = "units"
        if key in table:
            kw["units"] = _units(table[key])
        key = "functions"
        if key in table:
            kw["functions"] = _functions(table[key])
        key = "read_only"
        if key in table:
            if not isinstance(table[key], bool):
                raise ValueError(f"expected true or false, not {table[key]!r}")
            kw["read_only"] = table[key]
        tables = {}
        for key in TABLES:
            if key in table:
                tables[key] = _addresses(table[key])
        if tables:
            kw["tables"] = tables
    except ValueError as exc:
        raise fail(index, key, str(exc)) from None
    return Rule(name, **kw)


def parse_policy(text: str, source: str = "<policy>") -> Policy:
    """A policy from TOML text (``source`` names it in errors and in the log)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        match = re.search(r"\(at line (\d+), column \d+\)", str(exc))
        line = match.group(1) if match else None
        if line is None and "end of document" in str(exc):
            line = str(max(1, len(text.splitlines())))
        where = f"{source}:{line}" if line else source
        raise PolicyError(f"{where}: not valid TOML: {exc}") from None

    def fail(index: int, key: str | None, message: str) -> PolicyError:
        line = locate(text, "rule", key, index)
        where = f"{source}:{line}" if line else source
        return PolicyError(f"{where}: rule[{index}]: " + (f"{key}: " if key else "") + message)

    for key in doc:
        if key != "rule":
            line = next(
                (n + 1 for n, t in enumerate(text.splitlines()) if re.match(rf"\s*\[*{key}\b", t)),
                None,
            )
            where = f"{source}:{line}" if line else source
            raise PolicyError(f"{where}: {key}: unknown key (a policy is [[rule]] tables)")
    tables = doc.get("rule")
    if not isinstance(tables, list) or not tables:
        raise PolicyError(f"{source}: rule: no [[rule]] table (every request would be refused)")
    rules = [_rule(i, t, fail) for i, t in enumerate(tables)]
    names = [r.name for r in rules]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise fail(i, "name", f"{name!r} names two rules")
    return Policy(rules, source)


def load_policy(path: str | Path) -> Policy:
    """A policy from a TOML file; `PolicyError` names the file on any problem."""
    p = Path(path)
    text = read_text_file(p, PolicyError)
    return parse_policy(text, str(p))


__all__ = ["RULE_KEYS", "PolicyError", "load_policy", "parse_policy"]
