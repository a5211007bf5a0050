"""The `CommandSpec` most subcommands declare: `subcommand`."""

from __future__ import annotations

from pyrtu.cli.common import CommandSpec, Configure, Run, exit_code_table, guarded


def subcommand(
    name: str, help: str, configure: Configure, run: Run, description: str | None
) -> CommandSpec:
    """A subcommand whose ``run`` is `guarded` under ``name`` (errors become messages
    and exit codes) and whose ``--help`` shows ``description`` (the module's
    docstring) then the exit codes."""
    text = (description or "").strip() + "\n\n" + exit_code_table()
    return CommandSpec(name, help, configure, guarded(name, run), text)


__all__ = ["subcommand"]
