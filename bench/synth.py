"""Synthetic captures of mixed Modbus RTU traffic, for benchmarks (deterministic)."""

from __future__ import annotations

import random

import pyrtu


def mixed_traffic(size: int, seed: int = 1, noise: float = 0.01) -> bytes:
    """About `size` bytes: request/response pairs of FC 01-06, 15, 16, 23, 43 and
    exceptions, from 8 slaves, with ~`noise` of the frames followed by junk bytes."""
    rng = random.Random(seed)
    add = pyrtu.backend("python").add_crc
    out = bytearray()
    while len(out) < size:
        unit = rng.randint(1, 8)
        kind = rng.random()
        if kind < 0.45:
            count = rng.randint(1, 60)
            out += add(bytes([unit, 3, 0, rng.randint(0, 200), 0, count]))
            out += add(bytes([unit, 3, 2 * count]) + rng.randbytes(2 * count))
        elif kind < 0.60:
            count = rng.randint(1, 200)
            out += add(bytes([unit, 1, 0, 0, 0, count]))
            out += add(bytes([unit, 1, (count + 7) // 8]) + rng.randbytes((count + 7) // 8))
        elif kind < 0.75:
            req = add(bytes([unit, 6, 0, rng.randint(0, 255)]) + rng.randbytes(2))
            out += req + req
        elif kind < 0.85:
            count = rng.randint(1, 40)
            out += add(bytes([unit, 16, 0, 10, 0, count, 2 * count]) + rng.randbytes(2 * count))
            out += add(bytes([unit, 16, 0, 10, 0, count]))
        elif kind < 0.92:
            out += add(bytes([unit, 4, 0, 0, 0, 2]))
            out += add(bytes([unit, 0x84, 2]))
        else:
            out += add(bytes([unit, 0x2B, 0x0E, 1, 0]))
            objs = b"".join(bytes([i, 5]) + b"pyrtu" for i in range(3))
            out += add(bytes([unit, 0x2B, 0x0E, 1, 1, 0, 0, 3]) + objs)
        if rng.random() < noise:
            out += rng.randbytes(rng.randint(1, 6))
    return bytes(out[:size])
