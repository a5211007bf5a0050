"""`pyrtu.rules`: length rules, at the path the documentation shows.

The code lives in `pyrtu.core.rules`; this module re-exports its public names.
"""

from pyrtu.core.rules import (
    BONFIGLIOLI as BONFIGLIOLI,
)
from pyrtu.core.rules import (
    CV100 as CV100,
)
from pyrtu.core.rules import (
    RULE_COUNT as RULE_COUNT,
)
from pyrtu.core.rules import (
    RULE_FIXED as RULE_FIXED,
)
from pyrtu.core.rules import (
    RULE_NONE as RULE_NONE,
)
from pyrtu.core.rules import (
    LengthRule as LengthRule,
)
from pyrtu.core.rules import (
    RuleTable as RuleTable,
)
from pyrtu.core.rules import (
    check_rules as check_rules,
)

__all__ = [
    "BONFIGLIOLI",
    "CV100",
    "RULE_COUNT",
    "RULE_FIXED",
    "RULE_NONE",
    "LengthRule",
    "RuleTable",
    "check_rules",
]
