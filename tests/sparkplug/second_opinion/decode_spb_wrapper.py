"""Run by tests/sparkplug/test_sparkplug_second_opinion.py in mqtt-spb-wrapper's
own virtual environment: decodes the edge node's messages with its
`SpbPayloadParser` (protobuf 3.20's MessageToDict, then its own value decoding).

stdin: JSON [[kind, device, hex payload], ...]; stdout: JSON, per message the
parser's dictionary (None when it cannot parse it)."""

import json
import sys

from mqtt_spb_wrapper.spb_base import SpbPayloadParser


def main() -> None:
    out = []
    for _kind, _device, hexed in json.load(sys.stdin):
        out.append(SpbPayloadParser().parse_payload(bytes.fromhex(hexed)))
    json.dump(out, sys.stdout, default=str)


main()
