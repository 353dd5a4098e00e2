"""Messages: forms, round trips, errors and p-values."""

import math

import pytest
import torch

from gsw.stats import binomial_p_value, fisher_combined_p_value
from gsw.mark.message import (as_message, message_from_hex,
                          message_from_key, message_to_hex, random_message)


def test_hex_round_trip_and_forms() -> None:
    m = as_message("0xDEADbeef", 32)
    assert message_to_hex(m) == "deadbeef"
    assert torch.equal(message_from_hex("deadbeef", 32), m)
    assert torch.equal(as_message(m.tolist(), 32), m)
    assert torch.equal(as_message("key:studio-secret", 48), message_from_key("studio-secret", 48))
    assert not torch.equal(message_from_key("a", 64), message_from_key("b", 64))
    assert torch.equal(random_message(32, seed=3), random_message(32, seed=3))


@pytest.mark.parametrize("bad, match", [("abc", "hex digits"), ("zzzzzzzz", "hex digits"),
                                        ([0, 1, 2] + [0] * 29, "0 or 1"), ([0, 1], "expected 32")])
def test_bad_messages_are_rejected(bad, match) -> None:
    with pytest.raises(ValueError, match=match):
        as_message(bad, 32)


def test_binomial_p_value_known_values() -> None:
    assert binomial_p_value(32, 32) == pytest.approx(2.0 ** -32)
    assert binomial_p_value(0, 32) == pytest.approx(1.0)
    # P(X >= 30 | 32) = (C(32,30) + C(32,31) + 1) / 2^32 = 529 / 2^32
    assert binomial_p_value(30, 32) == pytest.approx(529 / 2 ** 32)
    # The 1e-6 thresholds of the paper: 30/32, 41/48, 51/64 bits are the first at or below 1e-6.
    for k, m in [(30, 32), (41, 48), (51, 64)]:
        assert binomial_p_value(k, m) <= 1e-6 < binomial_p_value(k - 1, m)


def test_fisher_combination() -> None:
    assert fisher_combined_p_value([0.3]) == pytest.approx(0.3)
    # two p-values: p = x (1 - ln x) with x = p1 p2
    x = 0.1 * 0.2
    assert fisher_combined_p_value([0.1, 0.2]) == pytest.approx(x * (1 - math.log(x)))


def test_default_messages_are_secret_and_fresh(monkeypatch) -> None:
    import secrets

    drawn = [random_message(64) for _ in range(3)]
    assert all(not torch.equal(a, b) for i, a in enumerate(drawn) for b in drawn[i + 1:])
    assert not torch.equal(as_message(None, 64), as_message(None, 64))
    # the bits come from the OS entropy pool (secrets), whatever torch's global seed
    monkeypatch.setattr(secrets, "randbits", lambda k: (1 << k) - 1)
    torch.manual_seed(0)
    assert torch.equal(as_message(None, 32), torch.ones(32))
    assert torch.equal(random_message(32, seed=5), random_message(32, seed=5))  # seeded: public, reproducible
