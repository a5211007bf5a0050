"""Deprecated path: `pyrtu.rules` (length rules).  Each name used here warns
(`DeprecationWarning`) naming its one public path: ``import pyrtu``'s own name
(`_ROOT`), else `pyrtu.core.rules`."""

from __future__ import annotations

from pyrtu.core._deprecated import renamed

#: the names `import pyrtu` has
_ROOT = ("BONFIGLIOLI", "CV100", "LengthRule")
#: the names only pyrtu.core.rules has
_HOME = ("RULE_COUNT", "RULE_FIXED", "RULE_NONE", "RuleTable", "check_rules")

__getattr__ = renamed(
    __name__,
    {
        **{name: ("pyrtu", name) for name in _ROOT},
        **{name: ("pyrtu.core.rules", name) for name in _HOME},
    },
)
__all__ = [*_ROOT, *_HOME]
