"""Watermark messages: bits, hex strings and secret keys.

A message is a [k] float tensor of 0/1 bits. :func:`as_message` accepts bits, a hex string of
exactly k/4 digits or a secret key string (hashed with SHA-256 into k bits).

Messages are secrets: without one, :func:`as_message` draws a fresh message from the operating system's
entropy pool (:mod:`secrets`), never from a seed, so two embeds never share a message by accident. A
seeded message (:func:`random_message` with ``seed``) is reproducible and therefore public: for tests,
benchmarks and ``gsw demo`` only.
"""

from __future__ import annotations

import hashlib
import secrets
from typing import Sequence, Union

import torch
from torch import Tensor


MessageLike = Union[None, str, Sequence[int], Tensor]


def random_message(num_bits: int, *, seed: int | None = None) -> Tensor:
    """A uniformly random [num_bits] 0/1 message.

    Args:
        num_bits: message length.
        seed: None (default): a secret message, each bit from the OS entropy pool (:func:`secrets.randbits`);
            an int: a reproducible, public message (torch generator seeded with it).
    """
    if num_bits <= 0:
        raise ValueError(f"num_bits must be positive, got {num_bits}")
    if seed is None:
        value = secrets.randbits(num_bits)
        return torch.tensor([(value >> i) & 1 for i in range(num_bits)], dtype=torch.float32)
    gen = torch.Generator().manual_seed(seed)
    return torch.randint(0, 2, (num_bits,), generator=gen).float()


def message_from_key(key: str, num_bits: int) -> Tensor:
    """Derives a [num_bits] message from a secret key string (SHA-256, repeated if needed)."""
    bits: list[int] = []
    counter = 0
    while len(bits) < num_bits:
        digest = hashlib.sha256(f"{counter}:{key}".encode()).digest()
        bits += [(byte >> i) & 1 for byte in digest for i in range(8)]
        counter += 1
    return torch.tensor(bits[:num_bits], dtype=torch.float32)


def redrawn_message(message: Tensor, attempt: int) -> Tensor:
    """The ``attempt``-th replacement of a drawn ``message`` [k]: derived from it with SHA-256
    (:func:`message_from_key`), so a replacement is as secret as the message and uniform when the message was, and
    every worker and rerun derives the same one."""
    return message_from_key(f"gsw-redraw:{attempt}:{message_to_hex(message)}", message.numel())


def message_to_hex(bits: Tensor) -> str:
    """[k] bits (k a multiple of 4, most significant bit first) -> hex string of k/4 digits."""
    b = [int(v) for v in (bits.detach().cpu().flatten() > 0.5).tolist()]
    if len(b) % 4:
        raise ValueError(f"hex needs a multiple of 4 bits, got {len(b)}")
    return "".join(f"{int(''.join(map(str, b[i:i + 4])), 2):x}" for i in range(0, len(b), 4))


def message_from_hex(text: str, num_bits: int) -> Tensor:
    """Hex string of num_bits/4 digits -> [num_bits] bits (most significant bit first)."""
    digits = text.lower().removeprefix("0x")
    if len(digits) * 4 != num_bits or any(c not in "0123456789abcdef" for c in digits):
        raise ValueError(f"a {num_bits}-bit message needs exactly {num_bits // 4} hex digits, got {text!r}")
    return torch.tensor([(int(c, 16) >> (3 - i)) & 1 for c in digits for i in range(4)],
                        dtype=torch.float32)


def as_message(message: MessageLike, num_bits: int, *, seed: int | None = None) -> Tensor:
    """Normalises any accepted message form to a [num_bits] float 0/1 tensor.

    Args:
        message: None (a fresh secret message, :func:`random_message`), a hex string (`0x` optional, num_bits/4 digits), `key:<secret>`
            (derived from the secret), or a sequence/tensor of num_bits 0/1 values.
        num_bits: message length.
        seed: when `message` is None, a seed makes the message reproducible (and public: tests, demo);
            without one it is secret.

    Raises:
        ValueError: wrong length, non-binary values or malformed hex.
    """
    if num_bits <= 0:
        raise ValueError(f"num_bits must be positive, got {num_bits}")
    if message is None:
        return random_message(num_bits, seed=seed)
    if isinstance(message, str):
        if message.startswith("key:"):
            return message_from_key(message[4:], num_bits)
        return message_from_hex(message, num_bits)
    try:
        bits = torch.as_tensor(message, dtype=torch.float32).flatten()
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"message must be a hex string, 'key:<secret>' or {num_bits} bits (0/1), "
                         f"got {type(message).__name__} ({exc})") from None
    if bits.numel() != num_bits:
        raise ValueError(f"message has {bits.numel()} bits, expected {num_bits}")
    if not torch.all((bits == 0) | (bits == 1)):
        raise ValueError("message bits must be 0 or 1")
    return bits
