"""The benchmark suite for users (``pyrtu bench``): what pyrtu gains on this machine
and a check of the user's own line.

=========  ==================================================================
module     concern
=========  ==================================================================
`timer`    timing a call: batches for a budget, the median per call
`suite`    the core against its fallback and the installed peers
`line`     the line check of one device (serial port or ``tcp://``)
`report`   the terminal table, JSON, the HTML report with plots
=========  ==================================================================

The developers' benchmarks, which write bench/RESULTS.md, are the repository's
``bench/`` folder, not this package.
"""

from pyrtu.bench.line import LineReport, check_serial, check_tcp
from pyrtu.bench.suite import PARTS, Row, SuiteResult, run_suite

__all__ = ["PARTS", "LineReport", "Row", "SuiteResult", "check_serial", "check_tcp", "run_suite"]
