"""`pyrtu.data`: register data helpers, at the path the documentation shows.

The code lives in `pyrtu.pdu.data`; this module re-exports its public names.
"""

from pyrtu.pdu.data import (
    FLOAT32_MAX as FLOAT32_MAX,
)
from pyrtu.pdu.data import (
    KINDS as KINDS,
)
from pyrtu.pdu.data import (
    ORDERS as ORDERS,
)
from pyrtu.pdu.data import (
    decode_float32 as decode_float32,
)
from pyrtu.pdu.data import (
    decode_int32 as decode_int32,
)
from pyrtu.pdu.data import (
    decode_string as decode_string,
)
from pyrtu.pdu.data import (
    decode_uint32 as decode_uint32,
)
from pyrtu.pdu.data import (
    decode_values as decode_values,
)
from pyrtu.pdu.data import (
    encode_float32 as encode_float32,
)
from pyrtu.pdu.data import (
    encode_int32 as encode_int32,
)
from pyrtu.pdu.data import (
    encode_string as encode_string,
)
from pyrtu.pdu.data import (
    encode_uint32 as encode_uint32,
)
from pyrtu.pdu.data import (
    encode_values as encode_values,
)

__all__ = [
    "FLOAT32_MAX",
    "KINDS",
    "ORDERS",
    "decode_float32",
    "decode_int32",
    "decode_string",
    "decode_uint32",
    "decode_values",
    "encode_float32",
    "encode_int32",
    "encode_string",
    "encode_uint32",
    "encode_values",
]
