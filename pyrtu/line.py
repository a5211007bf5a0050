"""`pyrtu.line`: the line object, LineConfig, at the path the documentation shows.

The code lives in `pyrtu.core.line`; this module re-exports its public names.
"""

from pyrtu.core.line import (
    LINE_DEFAULTS as LINE_DEFAULTS,
)
from pyrtu.core.line import (
    MAX_BAUDRATE as MAX_BAUDRATE,
)
from pyrtu.core.line import (
    MIN_BAUDRATE as MIN_BAUDRATE,
)
from pyrtu.core.line import (
    MODES as MODES,
)
from pyrtu.core.line import (
    FormatKeywords as FormatKeywords,
)
from pyrtu.core.line import (
    FramerKeywords as FramerKeywords,
)
from pyrtu.core.line import (
    LineConfig as LineConfig,
)
from pyrtu.core.line import (
    LineKeywords as LineKeywords,
)
from pyrtu.core.line import (
    check_baudrate as check_baudrate,
)
from pyrtu.core.line import (
    check_bytesize as check_bytesize,
)
from pyrtu.core.line import (
    check_keywords as check_keywords,
)
from pyrtu.core.line import (
    check_mode as check_mode,
)
from pyrtu.core.line import (
    check_parity as check_parity,
)
from pyrtu.core.line import (
    check_stopbits as check_stopbits,
)
from pyrtu.core.line import (
    check_timing as check_timing,
)
from pyrtu.core.line import (
    line_from as line_from,
)
from pyrtu.core.line import (
    split_field_error as split_field_error,
)

__all__ = [
    "LINE_DEFAULTS",
    "MAX_BAUDRATE",
    "MIN_BAUDRATE",
    "MODES",
    "FormatKeywords",
    "FramerKeywords",
    "LineConfig",
    "LineKeywords",
    "check_baudrate",
    "check_bytesize",
    "check_keywords",
    "check_mode",
    "check_parity",
    "check_stopbits",
    "check_timing",
    "line_from",
    "split_field_error",
]
