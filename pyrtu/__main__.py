"""``python -m pyrtu``: the pyrtu command line."""

from pyrtu.cli import main

raise SystemExit(main())
