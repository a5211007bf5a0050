"""The drivers of the serial line and the masters: thin interpreters of the protocols' actions.

The other I/O of pyrtu lives with its subsystem: `pyrtu.tcp`, `pyrtu.gateway`, `pyrtu.vbus`,
`pyrtu.poller`, `pyrtu.bridge` and the commands of `pyrtu.cli`.

`port` (the serial port), `links` (a master's transport: serial, ``tcp://``,
``rtu+tcp://``), `master` (`Master`) and `sync_io` (its blocking loop), `aio`
(`AsyncMaster`, `AsyncSlave`, the asyncio loop helpers), `slave`/`aio_slave`/
`slave_base` (the slaves), `_ptimer` (exact timers on any asyncio loop),
`reconnect` (the one retry schedule for ports that fail).
"""
