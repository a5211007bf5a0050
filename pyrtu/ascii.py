"""`pyrtu.ascii`: Modbus ASCII framing, at the path the documentation shows.

The code lives in `pyrtu.core.ascii`; this module re-exports its public names.
"""

from pyrtu.core.ascii import (
    ASCII_MAX_FRAME as ASCII_MAX_FRAME,
)
from pyrtu.core.ascii import (
    INTER_CHAR_LIMIT as INTER_CHAR_LIMIT,
)
from pyrtu.core.ascii import (
    AsciiCore as AsciiCore,
)
from pyrtu.core.ascii import (
    AsciiFramer as AsciiFramer,
)
from pyrtu.core.ascii import (
    ascii_message as ascii_message,
)
from pyrtu.core.ascii import (
    decode_ascii as decode_ascii,
)
from pyrtu.core.ascii import (
    delimiter_table as delimiter_table,
)
from pyrtu.core.ascii import (
    encode_ascii as encode_ascii,
)
from pyrtu.core.ascii import (
    make_framer as make_framer,
)

__all__ = [
    "ASCII_MAX_FRAME",
    "INTER_CHAR_LIMIT",
    "AsciiCore",
    "AsciiFramer",
    "ascii_message",
    "decode_ascii",
    "delimiter_table",
    "encode_ascii",
    "make_framer",
]
