"""The core: bytes and times in, frames out; no I/O and no clock.

The C binding (`_cext`, built from csrc/ by `_build_core`) and its pure-Python
twin (`_pure`) expose the same names; `_backend` chooses one, once, at import.
Above them: the framers (`framing`, `ascii`, `mbap`), the one feed-until-taken
loop (`feed`), the frame events (`frames`), the line (`line.LineConfig`), the
framer core's options derived from it (`options`), character timing (`timing`)
and the length rules (`rules`).  Nothing here imports another layer of pyrtu.
"""
