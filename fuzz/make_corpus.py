"""Write the seed corpora of the fuzz harnesses from the manuals' telegrams.

The telegrams are those of tests/vectors.py (every complete RTU frame printed in
the five drive manuals).  Each harness reads its own input layout (see the
comment at the top of fuzz/fuzz_<name>.c); this script lays the telegrams out in
those layouts, so that the fuzzer starts from real traffic.

    python fuzz/make_corpus.py          # writes fuzz/corpus/<harness>/seed-*
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from vectors import RTU  # noqa: E402

# fuzz_config's first byte: role (a % 3), baud index (a >> 2 & 7: 1200, 9600,
# 19200, ...), timing rule (a >> 5 & 1), strict (a >> 6 & 1); second byte 0: no
# hostile timing, no vendor rules.
MONITOR_19200 = 2 | 2 << 2
MASTER_9600 = 0 | 1 << 2
SLAVE_19200_STRICT = 1 | 2 << 2 | 1 << 6


def _sources() -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = {}
    for t in RTU:
        out.setdefault(t.source.replace("/", "-"), []).append(t.adu)
    return out


def stream_seeds() -> list[bytes]:
    seeds = []
    for adus in _sources().values():
        capture = b"".join(adus)
        for cfg in (MONITOR_19200, SLAVE_19200_STRICT):
            # untimed
            seeds.append(bytes([cfg, 0, 0]) + bytes(32) + b"\x00" + capture)
            # per-byte times: steps of 600 us (one character at 19200 baud, 8E1),
            # with a 5 ms step every 31 bytes
            desc = bytes([0, 0, 6] * 10 + [0, 50])
            seeds.append(bytes([cfg, 0, 1]) + desc + b"\x01" + capture)
        # a noisy join: telegrams separated by a byte of garbage
        noisy = b"\x55".join(adus)
        seeds.append(bytes([MONITOR_19200, 0, 2, 24]) + bytes([0, 60] * 15) + b"\x02" + noisy)
    return seeds


def framer_seeds() -> list[bytes]:
    seeds = []
    for adus in _sources().values():
        for cfg in (MONITOR_19200, MASTER_9600, SLAVE_19200_STRICT):
            ops = bytearray([cfg, 0])
            for adu in adus:
                for i in range(0, len(adu), 32):
                    piece = adu[i : i + 32]
                    # feed op: len = 1 + (op >> 3); time: small step (mode 0) of 2 ms
                    ops += bytes([(len(piece) - 1) << 3, 0, 20]) + piece
                ops += bytes([4 | 8])  # timer at the deadline
                ops += bytes([5, 2]) + adu[:2]  # the local side sent this
            ops += bytes([3])  # poll
            seeds.append(bytes(ops))
    return seeds


def predict_seeds() -> list[bytes]:
    seeds = []
    for adus in _sources().values():
        for adu in adus:
            for direction in (0, 1):
                seeds.append(bytes([0, direction]) + adu)
    # a vendor rule: FC 100 fixed 6 (request), count at 2 (response)
    seeds.append(bytes([2, 1, 0, 0, 0, 0, 6, 0, 100, 0, 2, 2, 1, 1, 0, 2, 1, 100, 0, 1]))
    return seeds


def crc_seeds() -> list[bytes]:
    seeds = []
    for adus in _sources().values():
        for adu in adus:
            seeds.append(b"\xff\xff\x00\x03\x00" + adu)
        seeds.append(b"\xff\xff\x00\x10\x05" + b"".join(adus))
    return seeds


def mbap_seeds() -> list[bytes]:
    """The manuals' PDUs as Modbus TCP (MBAP header, Messaging on TCP/IP V1.0b 3.1.3):
    byte 0 the role, byte 1 the read sizes (see fuzz_mbap.c), then the stream."""
    seeds = []
    for adus in _sources().values():
        stream = bytearray()
        for tid, adu in enumerate(adus):
            pdu = adu[1:-2]
            stream += tid.to_bytes(2, "big") + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big")
            stream += adu[:1] + pdu
        for role, reads in ((0, 0), (1, 7), (2, 3)):
            seeds.append(bytes([role, reads]) + bytes(stream))
    return seeds


def tcp_seeds() -> list[bytes]:
    """The manuals' answers as a Modbus TCP server sends them (MBAP header, Messaging
    on TCP/IP V1.0b 3.1.3): bytes 0..3 the awaited transaction id, the unit, the
    function and the read sizes (see fuzz_tcp.c), then the stream: the answers with
    transaction ids 0, 1, ... (the earlier ones late)."""
    seeds = []
    for adus in _sources().values():
        stream = bytearray()
        for tid, adu in enumerate(adus):
            pdu = adu[1:-2]
            stream += tid.to_bytes(2, "big") + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big")
            stream += adu[:1] + pdu
        last = adus[-1]
        seeds.append(bytes([len(adus) - 1, last[0], last[1] & 0x7F, 5]) + bytes(stream))
        seeds.append(bytes([0, adus[0][0], adus[0][1] & 0x7F, 0]) + bytes(stream))
    return seeds


def mux_seeds() -> list[bytes]:
    """The TCP seeds for the mux (see fuzz_mux.c): the same streams, after a byte of
    flags (the server shuts its end; timeout 0; a second transaction; a repeat) in
    place of the read sizes, and a seed for the pieces."""
    seeds = []
    for k, seed in enumerate(tcp_seeds()):
        seeds.append(seed[:3] + bytes([k % 8, 7 + k]) + seed[4:])
        seeds.append(seed[:3] + bytes([8 | k % 4, 7 + k]) + seed[4:])  # (repeated)
    return seeds


def vbus_seeds() -> list[bytes]:
    """The manuals' telegrams as request/answer transactions on a 2-drop wire at 115200
    baud (see fuzz_vbus.c): transmit on drop 0 then 1, a service after each."""
    seeds = []
    for adus in _sources().values():
        ops = bytearray([1, 0, 2])  # 2 drops, 86806 ns characters, 40 us lead
        for k, adu in enumerate(adus):
            body = adu[:79]
            ops += bytes([0, k % 2, len(body), 2]) + body  # transmit, 2 us later
            ops += bytes([2, 0]) + (len(body) * 9).to_bytes(2, "big")  # service
            ops += bytes([9, (k + 1) % 2, 0x10, 0x00, 2])  # the receiver reads it
        seeds.append(bytes(ops))
    return seeds


HARNESSES = {
    "stream": stream_seeds,
    "framer": framer_seeds,
    "predict": predict_seeds,
    "crc": crc_seeds,
    "mbap": mbap_seeds,
    "vbus": vbus_seeds,
    "tcp": tcp_seeds,
    "mux": mux_seeds,
}


def main() -> None:
    for name, make in HARNESSES.items():
        d = HERE / "corpus" / name
        d.mkdir(parents=True, exist_ok=True)
        for old in d.glob("seed-*"):
            old.unlink()
        seeds = make()
        for s in seeds:
            (d / f"seed-{hashlib.sha1(s).hexdigest()[:12]}").write_bytes(s)
        print(f"{name}: {len(seeds)} seeds, {sum(map(len, seeds))} bytes")


if __name__ == "__main__":
    main()
