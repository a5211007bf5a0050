"""Deprecated path: this module lives in `pyrtu.outbox.report` (the northbound-neutral
outbox, shared by every output).  Each name used here warns (`DeprecationWarning`)
naming its new path."""

from __future__ import annotations

from pyrtu.core._deprecated import moved

__getattr__ = moved(__name__, "pyrtu.outbox.report", ["Report", "Reporter"])
