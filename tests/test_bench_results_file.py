"""The benchmarks' results files: rows appended through the atomic writer."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from appliance.errors import OutputError
from bench.results_file import append_result, checkout_commit


def test_a_new_file_gets_the_header_then_the_row(tmp_path):
    out = tmp_path / "bench.md"
    append_result(out, "# Bench\n\n| a |\n|---|\n", "| 1 |\n")
    assert out.read_bytes() == b"# Bench\n\n| a |\n|---|\n| 1 |\n"
    assert [p.name for p in tmp_path.iterdir()] == ["bench.md"]


def test_an_existing_file_keeps_its_content_and_gains_the_row(tmp_path):
    out = tmp_path / "bench.md"
    out.write_bytes(b"# Earlier\r\n| 0 |\n")
    append_result(out, "# Not written\n", "| 1 |\n")
    append_result(out, "# Not written\n", "| 2 |\n")
    assert out.read_bytes() == b"# Earlier\r\n| 0 |\n| 1 |\n| 2 |\n"
    assert [p.name for p in tmp_path.iterdir()] == ["bench.md"]


def test_a_missing_folder_is_one_output_error(tmp_path):
    with pytest.raises(OutputError, match="does not exist"):
        append_result(tmp_path / "absent" / "bench.md", "", "| 1 |\n")


def test_a_folder_in_place_of_the_file_is_one_output_error(tmp_path):
    (tmp_path / "bench.md").mkdir()
    with pytest.raises(OutputError, match="bench.md"):
        append_result(tmp_path / "bench.md", "", "| 1 |\n")


def test_the_commit_of_a_checkout_and_of_a_folder_outside_one(tmp_path):
    assert re.fullmatch(r"[0-9a-f]{7,40}(\+dirty)?", checkout_commit(Path(__file__)))
    assert checkout_commit(tmp_path) == "unknown"
