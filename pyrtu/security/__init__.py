"""Modbus/TCP Security: the access policy of every listener (`pyrtu.security.policy`,
sans-I/O), its file (`pyrtu.security.policy_file`) and the audit trail of writes
(`pyrtu.security.audit`).
"""

from __future__ import annotations

from pyrtu.security.audit import AuditTrail, audit_record
from pyrtu.security.policy import Decision, Identity, Policy, Rule
from pyrtu.security.policy_file import PolicyError, load_policy, parse_policy

__all__ = [
    "AuditTrail",
    "Decision",
    "Identity",
    "Policy",
    "PolicyError",
    "Rule",
    "audit_record",
    "load_policy",
    "parse_policy",
]
