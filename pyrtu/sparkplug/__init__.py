"""``pyrtu bridge`` as a Sparkplug B 3.0 edge node (a ``[sparkplug]`` table; docs/sparkplug.md).

==================  ===============================================================
`sparkplug_b.proto` the payload schema, written from the specification (chapter 6)
`payload`           its message classes, built at run time with ``protobuf``
`config`            `SparkplugConfig`: the ``[sparkplug]`` table; `load_sparkplug_config`
`metrics`           a point as a metric: name, alias, datatype, properties (sans-I/O)
`session`           `EdgeSession`: topics, seq, bdSeq, births, deaths, data (sans-I/O)
`node`              `EdgeNode`: the session on the poller, the shared outbox and MQTT
==================  ===============================================================

Needs ``paho-mqtt`` and ``protobuf``: ``pip install 'pyrtu[sparkplug]'``.
"""

from pyrtu.core._lazy import lazy_attributes

#: the submodules on first use (``pyrtu.sparkplug.payload`` after ``import pyrtu``)
__getattr__ = lazy_attributes(__name__)
