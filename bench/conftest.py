"""Benchmarks: run with `python -m pytest bench -p no:cacheprovider --benchmark-json=...`.

They are measurements, not tests: targets live in bench/RESULTS.md, written by
bench/report.py from one run, never asserted here.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
