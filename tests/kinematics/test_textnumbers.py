"""Tests for kinematics.textnumbers: naming the field of a text line that is not a number."""

from kinematics.textnumbers import first_non_number, is_float


def test_is_float_accepts_what_float_accepts():
    assert all(is_float(s) for s in ("1", "-2.5e-3", "nan", "inf", " 3 "))
    assert not any(is_float(s) for s in ("", "x", "1,5", "0x10", "1.2.3"))


def test_first_non_number_names_the_first_bad_field():
    assert first_non_number(["1.0", "2", "abc", "x"]) == "abc"
    assert first_non_number(["1.0", "2", "3e4"]) is None
    assert first_non_number([]) is None
