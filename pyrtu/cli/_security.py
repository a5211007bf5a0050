"""The listeners' access options, shared by ``pyrtu gateway`` and ``pyrtu simulate
--tcp``: ``--policy FILE`` (`pyrtu.security.policy_file`), ``--read-only`` (the
one-flag policy, or every rule of the file made read-only), ``--audit FILE|-``
(the JSON lines of executed writes) and ``--tls-listen HOST:PORT`` with
``--tls-cert``, ``--tls-key`` and ``--tls-ca`` (Modbus/TCP Security).  A refused
request is one line on stderr (a JSON ``denied`` line with ``--json``) once per
client and reason; a listener beyond loopback with no policy says so once at the
start (docs/security.md)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from pyrtu.cli.common import emit
from pyrtu.security.audit import AuditTrail
from pyrtu.security.policy import Decision, Identity, Policy, beyond_loopback
from pyrtu.security.policy_file import load_policy
from pyrtu.security.tls import MBAPS_PORT, TlsListen, server_context

#: the files of ``--tls-listen``
TLS_FILES = ("--tls-cert", "--tls-key", "--tls-ca")


def add_security_options(
    p: argparse.ArgumentParser, listen_address: Callable[[str], tuple[str, int]]
) -> None:
    """The options; ``listen_address``: the parser of HOST:PORT (the command's)."""
    g = p.add_argument_group("access and TLS (docs/security.md)")
    g.add_argument(
        "--policy", metavar="FILE",
        help="access policy (TOML): which clients or roles may use which units, "
        "functions and addresses; any other request is answered exception 01",
    )  # fmt: skip
    g.add_argument(
        "--read-only", action="store_true",
        help="refuse every write (exception 01); with --policy, every rule reads only",
    )  # fmt: skip
    g.add_argument(
        "--audit", metavar="FILE|-",
        help="append every executed write as a JSON line to FILE (-: stderr)",
    )  # fmt: skip
    g.add_argument(
        "--tls-listen", type=listen_address, metavar="HOST:PORT",
        help="also listen for Modbus/TCP Security (TLS, mutual authentication; the "
        f"standard port is {MBAPS_PORT}); needs --tls-cert, --tls-key and --tls-ca",
    )  # fmt: skip
    g.add_argument("--tls-cert", metavar="FILE", help="the listener's certificate (PEM)")
    g.add_argument("--tls-key", metavar="FILE", help="the listener's private key (PEM)")
    g.add_argument(
        "--tls-ca", metavar="FILE",
        help="the CA (PEM) that signs the clients' certificates; a client without one is refused",
    )  # fmt: skip


@dataclass
class ListenerSecurity:
    """The policy and audit trail of a command's listeners, and its messages."""

    command: str
    json: bool
    policy: Policy | None
    audit: AuditTrail | None
    tls: TlsListen | None = None

    def server_kwargs(self) -> dict[str, Any]:
        """The keywords of `pyrtu.gateway.Gateway` and `pyrtu.tcp.server.TcpServer`
        (the TLS listener is ``tls``, a keyword of their ``start``)."""
        return {"policy": self.policy, "audit": self.audit, "on_denied": self.denied}

    def denied(self, who: Identity, decision: Decision) -> None:
        """A request refused (the gateway calls this once per client and reason)."""
        if self.json:
            emit({"type": "denied", "client": who.address, "role": who.role,
                  "subject": who.subject, "kind": decision.kind,
                  "reason": decision.reason})  # fmt: skip
        else:
            how = "" if decision.kind == "tls_handshake" else " (exception 01)"
            print(f"pyrtu {self.command}: refused{how} {who.describe()}: "
                  f"{decision.reason}", file=sys.stderr, flush=True)  # fmt: skip

    def warn_if_open(self, listeners: Iterable[tuple[str, int] | None]) -> None:
        """One line when a listener is reachable beyond loopback and no policy guards it."""
        if self.policy is not None:
            return
        for where in listeners:
            if where is not None and beyond_loopback(where[0]):
                print(f"pyrtu {self.command}: warning: listening on {where[0]}:{where[1]} "
                      "with no access policy: any client that reaches it may write "
                      "(--policy FILE or --read-only)", file=sys.stderr, flush=True)  # fmt: skip
                return

    def close(self) -> None:
        if self.audit is not None:
            self.audit.close()


def open_security(args: argparse.Namespace, command: str) -> ListenerSecurity:
    """The options' policy and audit trail; ValueError naming the flag or
    file:line: key (exit 2) before anything listens."""
    policy = load_policy(args.policy) if args.policy is not None else None
    if args.read_only:
        policy = Policy.read_only() if policy is None else policy.restricted_to_reads()
    tls = None
    files = {flag: getattr(args, flag[2:].replace("-", "_")) for flag in TLS_FILES}
    if args.tls_listen is not None:
        missing = [flag for flag, value in files.items() if value is None]
        if missing:
            raise ValueError(f"--tls-listen needs {', '.join(missing)}")
        context = server_context(args.tls_cert, args.tls_key, args.tls_ca)
        host, port = args.tls_listen
        tls = TlsListen(host, port, context)
    elif any(value is not None for value in files.values()):
        given = next(flag for flag, value in files.items() if value is not None)
        raise ValueError(f"{given} is for --tls-listen HOST:PORT: give it too")
    audit = None
    if args.audit is not None:
        try:
            audit = AuditTrail.open(args.audit)
        except OSError as exc:
            raise ValueError(f"--audit {args.audit}: {exc.strerror or exc}") from None
    return ListenerSecurity(command, bool(getattr(args, "json", False)), policy, audit, tls)


__all__ = ["ListenerSecurity", "add_security_options", "open_security"]
