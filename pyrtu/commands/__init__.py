"""The built-in ``pyrtu`` subcommands, one module per concern.

=============  =====================================================================
module         commands
=============  =====================================================================
`common`       shared: serial options, exit codes, errors, ``--json``, signals
`io`           ``read``, ``write``
`poll`         ``poll``
`scan`         ``scan``
`info`         ``info``
`sniff`        ``sniff``
`simulate`     ``simulate``
`vbus`         ``vbus``
=============  =====================================================================

Each module declares ``COMMANDS``, a tuple of `common.CommandSpec`; `pyrtu.cli`
registers them (``pyrtu demo`` is `pyrtu.demo`).
"""
