"""``python -m pyrtu``: the pyrtu command line."""

from pyrtu.cli import main

if __name__ == "__main__":  # imported (by a documentation tool, say): nothing runs
    raise SystemExit(main())
