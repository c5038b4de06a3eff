"""Every message from the page is checked: type, fields, value range, size; and rate-limited."""

from __future__ import annotations

import json
import random

import pytest

from hfrl_torch.interactive.messages import (
    Feedback,
    MessageError,
    Pause,
    Presence,
    RateLimiter,
    Speed,
    parse_message,
)


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        ('{"type": "feedback", "value": 1}', Feedback(1.0)),
        ('{"type": "feedback", "value": -1}', Feedback(-1.0)),
        ('{"type": "speed", "actions_per_s": 6.5}', Speed(6.5)),
        ('{"type": "pause", "paused": true}', Pause(True)),
        ('{"type": "presence", "here": false}', Presence(False)),
    ],
)
def test_valid_messages(raw, expected):
    assert parse_message(raw) == expected


@pytest.mark.parametrize(
    ("raw", "message"),
    [
        ("not json", "message is not valid JSON"),
        ("[1, 2]", "message is a JSON list; allowed: one JSON object"),
        ('{"type": "shout"}', "type='shout' is invalid; allowed: feedback, speed, pause, presence"),
        ('{"value": 1}', "type=None is invalid"),
        ('{"type": "feedback", "value": 5}', "value=5 is invalid; allowed: 1 (good) or -1 (bad)"),
        ('{"type": "feedback", "value": "1"}', "value='1' is invalid: must be a finite number"),
        ('{"type": "feedback", "value": true}', "value=True is invalid: must be a finite number"),
        ('{"type": "feedback", "value": 1, "extra": 0}', "a feedback message has fields"),
        ('{"type": "feedback"}', "a feedback message has fields ['type']"),
        ('{"type": "speed", "actions_per_s": 100}', "actions_per_s=100 is invalid: must be in 0.5..20"),
        ('{"type": "speed", "actions_per_s": NaN}', "message holds NaN; allowed: finite numbers"),
        (
            '{"type": "speed", "actions_per_s": 1e400}',
            "actions_per_s=inf is invalid: must be a finite number",
        ),
        ('{"type": "feedback", "value": -Infinity}', "message holds -Infinity; allowed: finite numbers"),
        ('{"type":"feedback","value":' + "9" * 400 + "}", "an integer of 400 digits; allowed: at most 6"),
        ('{"type": "speed", "actions_per_s": 1.' + "0" * 80 + "}", "a number of 82 characters"),
        ('{"type": [], "value": 1}', "type=[] is invalid; allowed: feedback"),
        ('{"type": {"a": 1}, "value": 1}', "type={'a': 1} is invalid"),
        ('{"type": 5, "value": 1}', "type=5 is invalid"),
        ("[" * 400 + "]" * 400, "message holds nested 400 deep; allowed: at most 4"),
        (
            '{"type": "feedback", "value": "' + "x" * 500 + '"}',
            "value='" + "x" * 36 + "... is invalid",
        ),
        ('{"type": "pause", "paused": null}', "paused=None is invalid: must be true or false"),
        ('{"type": "pause", "paused": 1}', "paused=1 is invalid: must be true or false"),
    ],
)
def test_malformed_messages_are_rejected_with_one_line(raw, message):
    with pytest.raises(MessageError) as info:
        parse_message(raw)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_oversized_messages_are_rejected_before_parsing():
    raw = json.dumps({"type": "feedback", "value": 1, "pad": "x" * 2000})
    with pytest.raises(MessageError, match="message of 2043 bytes is too large; allowed: at most 1024"):
        parse_message(raw, max_bytes=1024)


def test_rate_limiter_allows_bursts_then_the_rate():
    limiter = RateLimiter(rate=2.0, burst=3)
    assert [limiter.allow(0.0) for _ in range(4)] == [True, True, True, False]
    assert limiter.allow(0.5)  # one token back after half a second at 2 per second
    assert not limiter.allow(0.5)


def test_anything_the_page_sends_raises_message_error_only():
    rng = random.Random(8)
    atoms = [
        '{"type": "feedback", "value": 1}',
        "[",
        "]",
        "{",
        "}",
        '"',
        ",",
        ":",
        "9" * 30,
        "NaN",
        "1e999",
        "-",
    ]
    atoms += ["true", "null", '"type"', '"value"', '"speed"', "\\", "\u00e9", "\ud800", " "]
    for _ in range(3000):
        raw = "".join(rng.choice(atoms) for _ in range(rng.randint(0, 30)))
        try:
            parse_message(raw if rng.random() < 0.8 else raw.encode("utf-8", "surrogatepass"))
        except MessageError as e:
            assert "\n" not in str(e) and len(str(e)) < 200
    with pytest.raises(MessageError, match="message is a int; allowed: one JSON object as text"):
        parse_message(5)  # type: ignore[arg-type]
