"""The northbound-neutral outbox: what every northbound output (the JSON bridge, the
Sparkplug B edge node) shares between the poller and its broker.

============  =====================================================================
`outbox`      `Outbox`: the durable, bounded on-disk log of updates awaiting delivery
`report`      `Reporter`: report by exception, qualities (good, stale, bad)
`updates`     `PointUpdate`: a point's value as an outbox record, for any output
`service`     `OutboxService`: an output's run, halt and supervised tasks
============  =====================================================================

An output encodes what it stores (`updates` for a point update; the JSON bridge keeps
its own record form, read by every pyrtu since the format's version 1) and decodes it
when it publishes.  See docs/DESIGN.md.
"""

from pyrtu.core._lazy import lazy_attributes

#: the submodules on first use (``pyrtu.outbox.outbox`` after ``import pyrtu``)
__getattr__ = lazy_attributes(__name__)
