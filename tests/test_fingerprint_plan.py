"""gsw.fingerprint.plan: the recipients file, name rules and secret messages."""

from __future__ import annotations

import pytest

from gsw.fingerprint.plan import Recipient, assign_messages, check_recipients, parse_recipients, read_recipients
from gsw.mark.message import message_from_key, message_to_hex


def test_parses_names_messages_and_keys(tmp_path) -> None:
    path = tmp_path / "r.csv"
    path.write_text("# buyers\nrecipient,message,key\nalice,,\n\nbob,0123ABCD,\ncarol,,s3cret\n", encoding="utf-8")
    people = read_recipients(path)
    assert [p.name for p in people] == ["alice", "bob", "carol"]
    assert people[1].message == "0123ABCD" and people[2].key == "s3cret"
    assert people[0].where == f"{path}:3"
    assert "0123" not in repr(people[1]) and "s3cret" not in repr(people[2])  # secrets stay out of repr


def test_name_only_file() -> None:
    assert [p.name for p in parse_recipients("name\nx-1\ny.2\n")] == ["x-1", "y.2"]


@pytest.mark.parametrize("text, match", [
    ("recipient\nalice\nbob,extra\n", r"r\.csv:3: 2 fields"),
    ('recipient,message\n"alice,00000000\n', r"r\.csv:2: malformed CSV"),
    ("who,message\nalice,\n", r"r\.csv:1: the header"),
    ("recipient,recipient\nalice,bob\n", r"r\.csv:1: the header"),
    ("recipient\nAlice\nbob\nalice\n", r"r\.csv:4: duplicate recipient name 'alice' \(also at r\.csv:2"),
    ("recipient\n../evil\n", r"r\.csv:2: recipient name '\.\./evil'"),
    ("recipient\n.hidden\n", r"r\.csv:2: recipient name"),
    ("recipient\n12345\n", r"r\.csv:2: .*all digits"),
    ("recipient,message,key\nalice,00000000,k\n", r"r\.csv:2: give a message or a key"),
    ("# nothing\n\n", r"r\.csv: no recipients"),
])
def test_malformed_files_name_the_line(text: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        parse_recipients(text, "r.csv")


def test_not_utf8(tmp_path) -> None:
    path = tmp_path / "r.csv"
    path.write_bytes(b"recipient\n\xff\xfe\n")
    with pytest.raises(ValueError, match="not UTF-8"):
        read_recipients(path)


def test_assign_messages() -> None:
    people = check_recipients([Recipient("a"), Recipient("b", message="0x0123abcd"), Recipient("c", key="k"),
                               *[Recipient(f"r{i}") for i in range(50)]])
    out = assign_messages(people, 32)
    hexes = [r.message for r in out]
    assert hexes[1] == "0123abcd" and hexes[2] == message_to_hex(message_from_key("k", 32))
    assert all(len(h) == 8 and int(h, 16) >= 0 for h in hexes)
    assert len(set(hexes)) == len(hexes)
    assert all(r.key is None for r in out)
    drawn = assign_messages([Recipient("x")], 48)[0].message
    assert len(drawn) == 12
    with pytest.raises(ValueError, match="already issued"):
        assign_messages([Recipient("x", message="0123abcd", where="f:2")], 32, taken=["0123ABCD"])
    with pytest.raises(ValueError, match="f:2: message of 'x'"):
        assign_messages([Recipient("x", message="0123", where="f:2")], 32)
    with pytest.raises(ValueError, match="no recipients"):
        check_recipients([])


def test_messages_checked_on_reading_when_the_length_is_known(tmp_path) -> None:
    (tmp_path / "r.csv").write_text("recipient,message,key\nalice,0123abcd,\nbob,,secret\ncarol,012,\n")
    assert len(read_recipients(tmp_path / "r.csv")) == 3  # the length is not known yet: names and columns only
    with pytest.raises(ValueError, match="r.csv:4: message of 'carol': a 32-bit message needs exactly 8 hex"):
        read_recipients(tmp_path / "r.csv", 32)
    with pytest.raises(FileNotFoundError, match="recipients file .*none.csv: no such file"):
        read_recipients(tmp_path / "none.csv")
    with pytest.raises(FileNotFoundError, match="a folder, not a file"):
        read_recipients(tmp_path)
