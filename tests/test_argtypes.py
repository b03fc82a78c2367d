"""The shared argparse types (runtime/argtypes.py): bounds, refusals and one message style for every command."""

from __future__ import annotations

import argparse

import pytest

from dadiff.runtime.argtypes import float_in, int_in, non_negative_int, positive_int


def _refusal(parse, text: str) -> str:
    with pytest.raises(argparse.ArgumentTypeError) as info:
        parse(text)
    return str(info.value)


@pytest.mark.parametrize(("parse", "text", "value"), [
    (int_in(1, 20), "1", 1), (int_in(1, 20), "20", 20), (int_in(1, 20), " 7 ", 7),
    (int_in(0), "0", 0), (int_in(2), "1000000000000", 10**12), (int_in(-3, 3), "-3", -3),
    (positive_int, "1", 1), (non_negative_int, "0", 0),
])
def test_int_in_accepts_its_bounds(parse, text, value):
    result = parse(text)
    assert result == value and type(result) is int


@pytest.mark.parametrize(("parse", "text", "message"), [
    (int_in(1, 20), "0", "expected an integer from 1 to 20, got '0'"),  # below
    (int_in(1, 20), "21", "expected an integer from 1 to 20, got '21'"),  # above
    (int_in(1, 20), "1e3", "expected an integer from 1 to 20, got '1e3'"),
    (int_in(1, 20), "2.0", "expected an integer from 1 to 20, got '2.0'"),
    (int_in(1), "x", "expected an integer of at least 1, got 'x'"),
    (int_in(1), "", "expected an integer of at least 1, got ''"),
    (int_in(1), "nan", "expected an integer of at least 1, got 'nan'"),
    (int_in(0), "inf", "expected an integer of at least 0, got 'inf'"),
    (int_in(0), "-1", "expected an integer of at least 0, got '-1'"),
    (positive_int, "0", "expected an integer of at least 1, got '0'"),
    (non_negative_int, "-1", "expected an integer of at least 0, got '-1'"),
])
def test_int_in_refuses_naming_the_range_and_the_text(parse, text, message):
    assert _refusal(parse, text) == message


@pytest.mark.parametrize(("parse", "text", "value"), [
    (float_in(0, 10), "0", 0.0), (float_in(0, 10), "10", 10.0), (float_in(0, 10), "2.5", 2.5),
    (float_in(0, 10, open_low=True), "1e-9", 1e-9), (float_in(0, 10, open_low=True), "10", 10.0),
    (float_in(1), "1", 1.0), (float_in(1), "1e300", 1e300), (float_in(0, open_low=True), "0.001", 0.001),
    (float_in(-255, 255), "-255", -255.0),
])
def test_float_in_accepts_its_bounds(parse, text, value):
    assert parse(text) == value


@pytest.mark.parametrize(("parse", "text", "message"), [
    (float_in(0.5, 600), "0.4", "expected a number from 0.5 to 600, got '0.4'"),  # below
    (float_in(0.5, 600), "600.5", "expected a number from 0.5 to 600, got '600.5'"),  # above
    (float_in(0, 20, open_low=True), "0", "expected a number above 0 and at most 20, got '0'"),
    (float_in(0, 20, open_low=True), "20.1", "expected a number above 0 and at most 20, got '20.1'"),
    (float_in(0, open_low=True), "nan", "expected a number above 0, got 'nan'"),
    (float_in(0, open_low=True), "0", "expected a number above 0, got '0'"),
    (float_in(0, open_low=True), "inf", "expected a number above 0, got 'inf'"),
    (float_in(0), "-inf", "expected a number of at least 0, got '-inf'"),
    (float_in(0), "-0.1", "expected a number of at least 0, got '-0.1'"),
    (float_in(0), "fast", "expected a number of at least 0, got 'fast'"),
    (float_in(-255, 255), "1e308", "expected a number from -255 to 255, got '1e308'"),
    (float_in(-255, 255), "NaN", "expected a number from -255 to 255, got 'NaN'"),
])
def test_float_in_refuses_naming_the_range_and_the_text(parse, text, message):
    assert _refusal(parse, text) == message


def test_an_option_error_names_the_option_and_the_text(capsys):
    parser = argparse.ArgumentParser(prog="p")
    parser.add_argument("--frames", type=int_in(1, 20))
    with pytest.raises(SystemExit):
        parser.parse_args(["--frames", "0"])
    assert "argument --frames: expected an integer from 1 to 20, got '0'" in capsys.readouterr().err
