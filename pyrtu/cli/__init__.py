"""The ``pyrtu`` command line (also ``python -m pyrtu``).

Subcommands are registered in `COMMANDS` with `register` (or the `command`
decorator): a name, a one-line help, a function that adds the subcommand's
arguments to its parser, and a function that runs it and returns the exit status::

    def _configure_read(p: argparse.ArgumentParser) -> None:
        p.add_argument("port")

    @command("read", "read registers from a device", _configure_read)
    def _run_read(args: argparse.Namespace) -> int:
        ...
        return 0

The registry and `main` live in `app`; the built-in commands one module per
concern, each declaring its `common.CommandSpec` tuples in ``COMMANDS``, which
`app` registers:

=================  ==================================================================
module             commands
=================  ==================================================================
`app`              the registry, `build_parser`, `main`
`common`           shared: serial options, exit codes, errors, ``--json``, signals
`io`               ``read``, ``write``
`poll`             ``poll`` (`poll_config`: ``poll --config``, `poll_table`: its table)
`scan`, `info`     ``scan``, ``info``
`sniff`            ``sniff``
`simulate`         ``simulate`` (`_simulate_many`, `_simulate_tcp`, `_simulate_clash`)
`vbus`             ``vbus``
`gateway`          ``gateway``
`bridge`           ``bridge``
`demo`             ``demo``
=================  ==================================================================

The exit codes are those of `pyrtu.cli.common` (``pyrtu --help`` lists them).
"""

from pyrtu.cli.app import COMMANDS, Subcommand, build_parser, command, main, register
from pyrtu.core._deprecated import renamed

__all__ = ["COMMANDS", "Subcommand", "build_parser", "command", "main", "register"]

#: the name before issue 28's one name per concept (a drive's command word is a Command)
__getattr__ = renamed(__name__, {"Command": ("pyrtu.cli.app", "Subcommand")})
