"""Run by tests/sparkplug/test_sparkplug_second_opinion.py in pysparkplug's own
virtual environment: decodes the edge node's messages with pysparkplug.

stdin: JSON [[kind, device, hex payload], ...] in arrival order; stdout: JSON, per
message {seq, timestamp, metrics: [{name, alias, datatype, value, timestamp,
is_historical, is_null}]}; a DDATA is decoded with its device's last DBIRTH
(pysparkplug maps aliases to names and datatypes from it)."""

import json
import sys

import pysparkplug as spb

KINDS = {"NBIRTH": spb.NBirth, "DBIRTH": spb.DBirth, "DDATA": spb.DData, "NDEATH": spb.NDeath}


def main() -> None:
    births = {}
    out = []
    for kind, device, hexed in json.load(sys.stdin):
        raw = bytes.fromhex(hexed)
        birth = births.get(device) if kind == "DDATA" else None
        p = KINDS[kind].decode(raw, birth=birth) if kind == "DDATA" else KINDS[kind].decode(raw)
        if kind == "DBIRTH":
            births[device] = p
        metrics = []
        for m in p.metrics:
            value = m.value
            if isinstance(value, bytes):
                value = value.hex()
            metrics.append(
                {
                    "name": m.name,
                    "alias": m.alias,
                    "datatype": int(m.datatype),
                    "value": value,
                    "timestamp": m.timestamp,
                    "is_historical": m.is_historical,
                    "is_null": m.is_null,
                }
            )
        out.append({"seq": getattr(p, "seq", None), "timestamp": p.timestamp, "metrics": metrics})
    json.dump(out, sys.stdout)


main()
