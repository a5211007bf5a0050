"""The northbound-neutral outbox: what every northbound output (the JSON bridge, the
Sparkplug B edge node) shares between the poller and its broker.

============  =====================================================================
`outbox`      `Outbox`: the durable, bounded on-disk log of updates awaiting delivery
`report`      `Reporter`: report by exception, qualities (good, stale, bad)
`updates`     `PointUpdate`: a point's value as an outbox record, for any output
`service`     `OutboxService`: an output's run, halt and supervised tasks
============  =====================================================================

Every output stores point updates (`updates`) and makes of each what it publishes
(a topic and a JSON payload, a Sparkplug metric) when it publishes it; the JSON
bridge still delivers the records of its earlier form (a topic and a payload) that
an earlier pyrtu left in an outbox.  See docs/DESIGN.md.
"""

from pyrtu.core._lazy import lazy_attributes

#: the submodules on first use (``pyrtu.outbox.outbox`` after ``import pyrtu``)
__getattr__ = lazy_attributes(__name__)
