"""`pyrtu.timing`: character and silence times, at the path the documentation shows.

The code lives in `pyrtu.core.timing`; this module re-exports its public names.
"""

from pyrtu.core.timing import (
    BYTESIZES as BYTESIZES,
)
from pyrtu.core.timing import (
    MAX_BAUDRATE as MAX_BAUDRATE,
)
from pyrtu.core.timing import (
    MIN_BAUDRATE as MIN_BAUDRATE,
)
from pyrtu.core.timing import (
    MODES as MODES,
)
from pyrtu.core.timing import (
    PARITIES as PARITIES,
)
from pyrtu.core.timing import (
    STOPBITS as STOPBITS,
)
from pyrtu.core.timing import (
    TIMING_RULES as TIMING_RULES,
)
from pyrtu.core.timing import (
    Timing as Timing,
)
from pyrtu.core.timing import (
    apply_overrides as apply_overrides,
)
from pyrtu.core.timing import (
    bits_per_char as bits_per_char,
)
from pyrtu.core.timing import (
    check_baudrate as check_baudrate,
)
from pyrtu.core.timing import (
    check_bytesize as check_bytesize,
)
from pyrtu.core.timing import (
    check_mode as check_mode,
)
from pyrtu.core.timing import (
    check_parity as check_parity,
)
from pyrtu.core.timing import (
    check_stopbits as check_stopbits,
)
from pyrtu.core.timing import (
    check_timing as check_timing,
)
from pyrtu.core.timing import (
    compute_timing as compute_timing,
)
from pyrtu.core.timing import (
    positive_seconds as positive_seconds,
)
from pyrtu.core.timing import (
    seconds_to_us as seconds_to_us,
)

__all__ = [
    "BYTESIZES",
    "MAX_BAUDRATE",
    "MIN_BAUDRATE",
    "MODES",
    "PARITIES",
    "STOPBITS",
    "TIMING_RULES",
    "Timing",
    "apply_overrides",
    "bits_per_char",
    "check_baudrate",
    "check_bytesize",
    "check_mode",
    "check_parity",
    "check_stopbits",
    "check_timing",
    "compute_timing",
    "positive_seconds",
    "seconds_to_us",
]
