"""`pyrtu.core._text`: the one reader of a user's text file and of a list of numbers
and ranges (the gateway's unit ids, a policy's addresses, templates, configurations)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pyrtu.core._text import number_ranges, read_text_file

MESSAGES = {"not_a_range": "bad {part!r}", "outside": "outside {part!r}"}


def test_numbers_and_ranges_in_any_base_with_spaces() -> None:
    assert number_ranges(" 1-3, 0x10 ,7", 0, 100, **MESSAGES) == (
        range(1, 4),
        range(16, 17),
        range(7, 8),
    )


def test_the_bounds_are_inclusive_and_exact() -> None:
    assert number_ranges("5-9", 5, 9, **MESSAGES) == (range(5, 10),)
    assert number_ranges("5,9", 5, 9, **MESSAGES) == (range(5, 6), range(9, 10))
    for outside in ("4", "10", "4-9", "5-10"):
        with pytest.raises(ValueError, match=rf"^outside '{outside}'$"):
            number_ranges(outside, 5, 9, **MESSAGES)


def test_a_descending_range_is_refused_and_an_equal_one_is_one_number() -> None:
    assert number_ranges("7-7", 0, 9, **MESSAGES) == (range(7, 8),)
    with pytest.raises(ValueError, match=r"^outside '8-7'$"):
        number_ranges("8-7", 0, 9, **MESSAGES)


@pytest.mark.parametrize("text", ["", "a", "1-", "-1", "1-2-3", "1,,2", "1.5"])
def test_what_is_no_number_or_range_names_the_part(text: str) -> None:
    with pytest.raises(ValueError, match=r"^bad '"):
        number_ranges(text, 0, 9, **MESSAGES)


class FileProblem(ValueError):
    pass


def test_a_file_is_read_as_utf8(tmp_path: Path) -> None:
    path = tmp_path / "a.toml"
    path.write_bytes("x = 'é'\n".encode())
    assert read_text_file(path, FileProblem) == "x = 'é'\n"


def test_each_problem_is_the_callers_error_naming_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "missing.toml"
    with pytest.raises(FileProblem, match=rf"^{missing}: no such file$"):
        read_text_file(missing, FileProblem)
    latin = tmp_path / "latin.toml"
    latin.write_bytes(b"x = '\xe9'\n")
    with pytest.raises(FileProblem, match=rf"^{latin}: not UTF-8 text \(.* at byte 5\)$"):
        read_text_file(latin, FileProblem)
    with pytest.raises(FileProblem, match=rf"^{tmp_path}: cannot read: "):
        read_text_file(tmp_path, FileProblem)  # a directory
