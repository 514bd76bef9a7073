"""Bounded input at the edge (issue 35): FIFOs and devices, files too large, image bombs, deeply nested
JSON and TOML, log records of another shape, options out of range, escapes in names, long names.

Every case of the catalogue in :mod:`bench.bounded_input` runs ``viper`` in a child process with a
60 s timeout and a 2 GiB address-space limit; it must end with one stderr line of the expected shape,
a non-zero exit and the folder as it was, or with the correct result; never a traceback, a hang or
2 GiB of memory.  The benchmark records each case's peak memory in bench/results/bounded_input.md.
"""

from __future__ import annotations

import fcntl
import os
import re

import pytest

from appliance.atomic import TMP_MARK, atomic_output, remove_stale_temporaries, temporary_name
from appliance.config import ConfigError, load_config
from appliance.errors import InputError
from appliance.inputs import MAX_NESTING, NestingError, check_image_pixels, check_nesting, nesting_depth
from bench.bounded_input import CATALOGUE, MEMORY_BYTES, build_shared, png_bytes, run_case, verdict


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    return build_shared(tmp_path_factory.mktemp("bounded-shared"))


@pytest.mark.parametrize("case", CATALOGUE, ids=[c.name for c in CATALOGUE])
def test_catalogue_case(case, shared, tmp_path):
    if any(n not in shared for n in case.needs):
        pytest.skip("the SRTM tiles of ../shared/data are absent")
    run, before, after = run_case(case, tmp_path, shared)
    assert run.returncode is not None, "hung past the timeout"
    assert run.peak_bytes < MEMORY_BYTES
    assert "Traceback" not in run.stderr
    if case.expect is None:
        assert run.returncode == case.ok_status, run.stderr
        assert re.search(case.expect_stdout, run.stdout), run.stdout
    else:
        assert run.returncode != 0
        assert len(run.stderr_lines) == 1, run.stderr
        assert re.match(r"viper [a-z]+: error: ", run.stderr_lines[0])
        assert re.search(case.expect, run.stderr_lines[0]), run.stderr_lines[0]
        assert after == before
        assert "\x1b" not in run.stderr
    assert verdict(case, run, before, after) == "ok"


def test_the_long_output_name_is_written_and_no_temporary_is_left(shared, tmp_path):
    case = next(c for c in CATALOGUE if c.name == "long-output-name")
    run, _, after = run_case(case, tmp_path, shared)
    assert run.returncode == 0
    assert after == {"s" * 246 + ".csv"}
    assert (tmp_path / ("s" * 246 + ".csv")).read_text().startswith("azimuth_deg,elevation_deg\n")


def test_nesting_is_counted_outside_strings_and_comments():
    assert nesting_depth('{"a": [1, {"b": "[[[[{{{{"}]}') == 3
    assert nesting_depth("a = '[[[[' # [[[[[[\n[t]\nb = [[1], \"]]]\"]\n") == 2
    assert nesting_depth('"\\"[[[" ') == 0
    check_nesting("[" * MAX_NESTING + "]" * MAX_NESTING)
    with pytest.raises(NestingError, match=f"nested {MAX_NESTING + 1} levels deep, more than {MAX_NESTING}"):
        check_nesting("[" * (MAX_NESTING + 1))


def test_a_config_nested_below_the_cap_still_parses(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[sim]\nleg_length_m = [100.0, 200.0] # ]]]]\n[session]\nbody_mask_deg = [[10.0, 20.0]]\n")
    assert load_config(cfg).session.body_mask_deg == ((10.0, 20.0),)
    cfg.write_text("[session]\nbody_mask_deg = " + "[" * 70 + "]" * 70 + "\n")
    with pytest.raises(ConfigError, match="not valid TOML: nested 70 levels deep"):
        load_config(cfg)


def test_the_image_header_is_checked_before_decoding():
    check_image_pixels(png_bytes(4000, 3000, 1), "ok.png")
    message = r"^big\.png: a 10000 x 6000 image has 60,000,000 pixels, more than 50,000,000$"
    with pytest.raises(InputError, match=message):
        check_image_pixels(png_bytes(10000, 6000, 1), "big.png")
    check_image_pixels(b"not an image", "x.bin")  # no header: the decoder says what it finds


def test_a_long_name_gets_a_short_temporary_and_its_stale_ones_are_still_removed(tmp_path):
    name = "é" * 120 + ".tif"  # 244 bytes
    tmp = temporary_name(name)
    assert len(tmp.encode()) <= 231 and tmp.startswith(".") and tmp.endswith(f"{TMP_MARK}.tif")
    assert temporary_name(name).split(".")[1] == tmp.split(".")[1]  # the same stem for the same name
    stale = tmp_path / tmp
    stale.write_bytes(b"killed writer")
    held = tmp_path / temporary_name(name)
    held.write_bytes(b"live writer")
    fd = os.open(held, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        assert remove_stale_temporaries(tmp_path, name) == [stale]
    finally:
        os.close(fd)
    held.unlink()
    with atomic_output(tmp_path / name) as t:
        t.write_bytes(b"data")
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_integers_beyond_64_bits_are_refused_by_name(tmp_path):
    # found by bench/edge_fuzz.py: a huge TOML integer reached math.isfinite and float() as OverflowError
    for table, key, value in (("estimator", "occlusion_weight", 10**400), ("logbook", "chunk_size_bytes", -(2**64))):
        path = tmp_path / "c.toml"
        path.write_text(f"[{table}]\n{key} = {value}\n")
        with pytest.raises(ConfigError, match=rf"{table}\.{key}: .*beyond"):
            load_config(path)
    path = tmp_path / "ok.toml"
    path.write_text("[logbook]\nchunk_size_bytes = 1048576\n")
    assert load_config(path).logbook.chunk_size_bytes == 1048576


def test_a_sidecar_number_beyond_floats_is_one_error(tmp_path):
    from appliance.vision.photo import read_orientation_file  # the photo reader loads OpenCV

    side = tmp_path / "p.json"
    side.write_text('{"yaw_deg": 1' + "0" * 400 + ', "pitch_deg": 0, "roll_deg": 0}')
    with pytest.raises(InputError, match="must be numbers"):
        read_orientation_file(side)


def test_a_camera_file_name_too_long_is_one_config_error(tmp_path):
    from appliance.vision.intrinsics import load_intrinsics

    with pytest.raises(ConfigError, match="cannot read the calibration file"):
        load_intrinsics(tmp_path / ("c" * 300 + ".toml"))


def _png_with_a_chunk_past_the_end(path) -> None:
    """A 48 x 24 PNG whose pixel chunk is renamed (an unknown critical chunk), then a chunk declaring 1 GiB
    of which 8 bytes are there: what the input fuzzer's mutations made of a small PNG."""
    import struct

    good = png_bytes(48, 24)
    idat, iend = good.find(b"IDAT"), good.rfind(b"IEND") - 4
    path.write_bytes(good[:idat] + b"IDAU" + good[idat + 4:iend] + struct.pack(">I", 1 << 30) + b"IEND" + bytes(8))


def test_a_png_chunk_declared_past_the_file_is_not_allocated(tmp_path):
    """OpenCV's PNG reader allocated the 1 GiB the chunk declares; the buffer it gets now ends before it."""
    from bench.bounded_input import run_viper

    _png_with_a_chunk_past_the_end(tmp_path / "forged.png")
    run = run_viper(["skyline", "forged.png", "--out", "s.csv"], tmp_path)
    assert run.returncode != 0 and len(run.stderr_lines) == 1, run.stderr
    assert re.match(r"viper skyline: error: forged\.png: not a readable image \(\d+ bytes\)", run.stderr_lines[0])
    assert run.peak_bytes < 512 << 20  # a file of 79 bytes; the decoder took over 1 GiB for it
    assert not (tmp_path / "s.csv").exists()


def test_bounded_png_cuts_at_the_first_chunk_past_the_end(tmp_path):
    from appliance.inputs import bounded_png

    good = png_bytes(48, 24)
    assert bounded_png(good) == good
    assert bounded_png(b"\xff\xd8\xff" + bytes(20)) == b"\xff\xd8\xff" + bytes(20)  # not a PNG: as it is
    _png_with_a_chunk_past_the_end(tmp_path / "forged.png")
    forged = (tmp_path / "forged.png").read_bytes()
    assert bounded_png(forged) == forged[:len(forged) - 16]  # before the length, type and 8 bytes of the chunk
    assert bounded_png(good[:-5]) == good[:good.rfind(b"IEND") - 4]  # a torn last chunk
