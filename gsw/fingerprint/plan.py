"""The recipients of a fingerprinting job: the recipients file, name rules, secret messages.

A recipients file is CSV (UTF-8) with a header row. The column ``recipient`` (the name; ``name`` and
``label`` are accepted too) is required; ``message`` (hex, ``num_bits / 4`` digits) and ``key`` (a secret
the message is derived from, :func:`gsw.mark.message.message_from_key`) are optional, at most one per
row. Recipients without either get a fresh message from :mod:`secrets`. Blank lines and lines starting
with ``#`` are skipped::

    recipient,message,key
    alice,,
    bob,0123abcd,
    carol,,carols-secret

A recipient's name is its output folder name and its registry label: letters, digits, ``.``, ``_`` and
``-`` (not starting with ``.``), at most 100 characters, not all digits; names must differ even ignoring
case (case-insensitive file systems).
"""

from __future__ import annotations

import csv
import io
import re
import secrets
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

__all__ = ["Recipient", "read_recipients", "parse_recipients", "check_recipients", "check_messages", "assign_messages"]

_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,99}")
_NAME_COLUMNS = ("recipient", "name", "label")


@dataclass(frozen=True)
class Recipient:
    """One recipient of a fingerprinting job.

    Attributes:
        name: folder name and registry label.
        message: the secret message as hex (``None``: not drawn yet; see :func:`assign_messages`); kept out
            of ``repr``.
        key: a secret the message is derived from, or None; kept out of ``repr``.
        where: where the recipient was defined (``file:line``), for error messages.
    """

    name: str
    message: str | None = field(default=None, repr=False)
    key: str | None = field(default=None, repr=False)
    where: str = ""


def _check_name(name: str, where: str) -> str:
    name = name.strip()
    if not name:
        raise ValueError(f"{where}: empty recipient name")
    if not _NAME.fullmatch(name):
        raise ValueError(f"{where}: recipient name {name!r} must be 1-100 letters, digits, '.', '_' or '-' "
                         "(not starting with '.'): it names the recipient's output folder")
    if name.isdigit():
        raise ValueError(f"{where}: recipient name {name!r} is all digits (it would read as a registry id); "
                         "add a letter")
    return name


def check_recipients(recipients: Sequence[Recipient]) -> list[Recipient]:
    """Checks names (rules above) and that no two recipients share a name, ignoring case.

    Raises:
        ValueError: a bad or duplicate name (both places named), or no recipients.
    """
    if not recipients:
        raise ValueError("no recipients given")
    seen: dict[str, Recipient] = {}
    out = []
    for i, r in enumerate(recipients):
        where = r.where or f"recipient {i + 1}"
        name = _check_name(r.name, where)
        if r.message is not None and r.key is not None:
            raise ValueError(f"{where}: give a message or a key for {name!r}, not both")
        other = seen.get(name.lower())
        if other is not None:
            raise ValueError(f"{where}: duplicate recipient name {name!r} (also at "
                             f"{other.where or 'an earlier recipient'}; names must differ ignoring case)")
        r = Recipient(name, r.message, r.key, where)
        seen[name.lower()] = r
        out.append(r)
    return out


def parse_recipients(text: str, source: str = "<recipients>") -> list[Recipient]:
    """Parses the CSV text of a recipients file (see the module docstring).

    Args:
        text: the file's content.
        source: its name in error messages.

    Returns:
        The recipients, in file order.

    Raises:
        ValueError: no header / no name column, an unknown column, a row with too many fields, a bad or
            duplicate name, both message and key (the error names ``source:line``).
    """
    lines = [(n, line) for n, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{source}: no recipients (expected a header row 'recipient[,message][,key]')")
    header_line, header = lines[0]
    columns = [c.strip().lower() for c in next(csv.reader(io.StringIO(header)))]
    names = [c for c in columns if c in _NAME_COLUMNS]
    unknown = [c for c in columns if c not in (*_NAME_COLUMNS, "message", "key")]
    if len(names) != 1 or unknown or len(set(columns)) != len(columns):
        raise ValueError(f"{source}:{header_line}: the header must name one of {', '.join(_NAME_COLUMNS)} and "
                         f"optionally message and key, each once (got {header.strip()!r})")
    recipients = []
    for n, line in lines[1:]:
        where = f"{source}:{n}"
        try:
            fields = next(csv.reader(io.StringIO(line), strict=True))
        except csv.Error as err:
            raise ValueError(f"{where}: malformed CSV ({err})") from None
        if len(fields) > len(columns):
            raise ValueError(f"{where}: {len(fields)} fields, the header has {len(columns)}")
        row = dict(zip(columns, [f.strip() for f in fields]))
        recipients.append(Recipient(row.get(names[0], ""), row.get("message") or None, row.get("key") or None,
                                    where))
    return check_recipients(recipients)


def read_recipients(path: str | Path, num_bits: int | None = None) -> list[Recipient]:
    """Reads and checks a recipients file (:func:`parse_recipients`; with ``num_bits``, its messages too:
    :func:`check_messages`).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not UTF-8, or malformed (the error names the file and line).
    """
    path = Path(path)
    if not path.is_file():
        what = "a folder, not a file" if path.is_dir() else "no such file"
        raise FileNotFoundError(f"recipients file {path}: {what}")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not UTF-8 text ({err})") from None
    recipients = parse_recipients(text, str(path))
    if num_bits is not None:
        check_messages(recipients, num_bits)
    return recipients


def check_messages(recipients: Sequence[Recipient], num_bits: int) -> None:
    """Checks the given and key-derived messages of ``recipients`` as :func:`assign_messages` will (length, hex
    digits, no two alike), before anything is written.

    Raises:
        ValueError: a malformed message (the error names its line), or two recipients with one message.
    """
    assign_messages([r for r in recipients if r.message is not None or r.key is not None], num_bits)


def assign_messages(recipients: Iterable[Recipient], num_bits: int, taken: Iterable[str] = ()) -> list[Recipient]:
    """The recipients with their message as hex: given, derived from the key, or drawn with :mod:`secrets`.

    Args:
        recipients: checked recipients.
        num_bits: message length (a multiple of 4).
        taken: hex messages already issued (e.g. in the registry for the same decoder): a drawn message
            avoids them and a given one that repeats one is refused.

    Raises:
        ValueError: a malformed message (the error names its line), or two recipients with one message.
    """
    from gsw.mark.message import as_message, message_from_key, message_to_hex

    used = {m.lower() for m in taken}
    out = []
    for r in recipients:
        if r.message is not None:
            try:
                hex_message = message_to_hex(as_message(r.message, num_bits))
            except ValueError as err:
                raise ValueError(f"{r.where}: message of {r.name!r}: {err}") from None
        elif r.key is not None:
            hex_message = message_to_hex(message_from_key(r.key, num_bits))
        else:
            hex_message = secrets.token_hex(num_bits // 8 + 1)[: num_bits // 4]
            while hex_message in used:
                hex_message = secrets.token_hex(num_bits // 8 + 1)[: num_bits // 4]
        if hex_message in used:
            raise ValueError(f"{r.where}: the message of {r.name!r} is already issued (two recipients would be "
                             "indistinguishable)")
        used.add(hex_message)
        out.append(Recipient(r.name, hex_message, None, r.where))
    return out
