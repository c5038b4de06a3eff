"""JSON within bounds: what the bounds allow round-trips; anything else is a JSONBoundsError, never another
exception (property tests)."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch.common.bounded_json import JSONBoundsError, json_depth, loads_bounded

SMALL = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**17), 10**17)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=20,
)


@settings(max_examples=300, deadline=None)
@given(SMALL)
def test_values_within_the_bounds_round_trip(value):
    text = json.dumps(value)
    if json_depth(text.encode()) <= 16:
        assert loads_bounded(text) == value
    else:
        with pytest.raises(JSONBoundsError, match="deep; allowed: at most 16"):
            loads_bounded(text)


@settings(max_examples=500, deadline=None)
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_any_text_gives_a_value_or_a_bounds_error(text):
    try:
        loads_bounded(text, max_depth=3, max_int_digits=4, max_number_chars=8)
    except JSONBoundsError as e:
        assert "\n" not in str(e)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("9" * 400, "an integer of 400 digits; allowed: at most 18"),
        ("-" + "9" * 19, "an integer of 19 digits"),
        ("[" * 5000 + "]" * 5000, "nested 5000 deep; allowed: at most 16"),
        ('{"a": ' * 17 + "1" + "}" * 17, "nested 17 deep"),
        ("1." + "0" * 50, "a number of 52 characters; allowed: at most 40"),
        ("NaN", "NaN; allowed: finite numbers"),
        ("[-Infinity]", "-Infinity; allowed"),
        ("{", "not JSON"),
        (b"\xff", "not UTF-8"),
    ],
)
def test_what_is_refused(text, match):
    with pytest.raises(JSONBoundsError, match=match):
        loads_bounded(text)


def test_brackets_inside_strings_do_not_count():
    assert loads_bounded(json.dumps({"s": "[" * 100})) == {"s": "[" * 100}
    assert json_depth(b'["\\"[[[", [1]]') == 2
