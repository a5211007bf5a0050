"""What users write, read one way everywhere (a leaf module): a UTF-8 file
(`read_text_file`: templates, configurations, policies) and a list of numbers and
ranges such as ``"1-10,20"`` (`number_ranges`: the gateway's unit ids, a policy's
addresses)."""

from __future__ import annotations

from pathlib import Path


def read_text_file(path: str | Path, error: type[ValueError]) -> str:
    """The text of a UTF-8 file; ``error`` names the file when it is missing, unreadable
    or not UTF-8 (the template loader's, the poller's configuration loader's and the
    policy loader's words)."""
    p = Path(path)
    try:
        return p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{p}: no such file") from None
    except UnicodeDecodeError as e:
        raise error(f"{p}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except OSError as e:
        raise error(f"{p}: cannot read: {e.strerror or e}") from None


def number_ranges(
    text: str, low: int, high: int, *, not_a_range: str, outside: str
) -> tuple[range, ...]:
    """The comma-separated parts of ``text`` as ranges: ``N`` is ``N..N``, ``A-B`` is
    ``A..B`` (inclusive; numbers as ``int(x, 0)`` reads them: ``0x10`` too).
    ValueError(``not_a_range``) for a part that is neither, ValueError(``outside``) for
    one outside ``low..high`` or not ascending; both messages are formatted with the
    ``part`` (white space stripped)."""
    ranges = []
    for part in text.split(","):
        part = part.strip()
        first_text, dash, last_text = part.partition("-")
        try:
            first = int(first_text, 0)
            last = int(last_text, 0) if dash else first
        except ValueError:
            raise ValueError(not_a_range.format(part=part)) from None
        if not low <= first <= last <= high:
            raise ValueError(outside.format(part=part))
        ranges.append(range(first, last + 1))
    return tuple(ranges)
