"""The registry of issued marks: round trip, secrecy, permissions, concurrency, bad files, locks."""

from __future__ import annotations

import hashlib
import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from gsw.mark.message import message_from_hex, message_from_key
from gsw.registry import (SCHEMA_VERSION, Mark, RegistryError, UnknownMarkError, default_registry_path,
                          hash_gaussians, hash_model_file, open_registry, shipped_decoder_sha256)
from helpers import random_model

SHA = "ab" * 32


def test_round_trip_by_id_and_label(tmp_path) -> None:
    path = tmp_path / "reg.sqlite"
    with open_registry(path) as reg:
        a = reg.add("alice", "0123abcd", decoder_sha256=SHA, model_hash="sha256:" + "0" * 64, width=800,
                    height=600, background=(1, 1, 1))
        b = reg.add("bob studio", torch.tensor([1, 0] * 24), decoder_sha256=SHA)
        c = reg.add("carol", "key:carol-secret", num_bits=64, decoder_sha256=SHA)
        assert len(reg) == 3 and a < b < c
    with open_registry(path, create=False) as reg:  # persisted
        alice = reg.get("alice")
        assert reg.get(a) == alice == reg.get(str(a))
        assert (alice.message_hex, alice.num_bits, alice.width, alice.height) == ("0123abcd", 32, 800, 600)
        assert alice.background == (1.0, 1.0, 1.0) and alice.model_hash == "sha256:" + "0" * 64
        assert torch.equal(alice.message, message_from_hex("0123abcd", 32))
        assert torch.equal(reg.get("bob studio").message, torch.tensor([1.0, 0.0] * 24))
        assert torch.equal(reg.get("carol").message, message_from_key("carol-secret", 64))
        assert [m.label for m in reg.list()] == ["alice", "bob studio", "carol"]
        assert [m.label for m in reg.list(num_bits=64)] == ["carol"]
        assert [m.label for m in reg.of_model("sha256:" + "1" * 64, "sha256:" + "0" * 64)] == ["alice"]
        assert reg.of_model("sha256:" + "1" * 64) == [] and reg.of_model() == []
        assert alice.created.endswith("+00:00") and alice.gsw_version
        with pytest.raises(UnknownMarkError, match="no mark with label 'dave'"):
            reg.get("dave")
        with pytest.raises(UnknownMarkError, match="no mark with id 99"):
            reg.get(99)


def test_messages_stay_out_of_repr_and_default_dicts(tmp_path) -> None:
    with open_registry(tmp_path / "reg.sqlite") as reg:
        reg.add("alice", "deadbeef", decoder_sha256=SHA)
        mark = reg.get("alice")
    assert "deadbeef" not in repr(mark) and "deadbeef" not in str(mark.to_dict())
    assert mark.to_dict(show_secret=True)["message_hex"] == "deadbeef"
    assert set(mark.to_dict()) == {f for f in Mark.__dataclass_fields__} - {"message_hex"}


def test_rejects_duplicates_and_bad_records_without_writing(tmp_path) -> None:
    with open_registry(tmp_path / "reg.sqlite") as reg:
        reg.add("alice", "0123abcd", decoder_sha256=SHA)
        with pytest.raises(ValueError, match="already registered"):
            reg.add("alice", "11111111", decoder_sha256=SHA)
        with pytest.raises(ValueError, match="indistinguishable"):
            reg.add("bob", "0123abcd", decoder_sha256=SHA)
        reg.add("bob", "0123abcd", decoder_sha256="cd" * 32)  # same bits, another decoder: a different mark
        with pytest.raises(ValueError, match="all digits"):
            reg.add("42", "22222222", decoder_sha256=SHA)
        with pytest.raises(ValueError, match="num_bits is required"):
            reg.add("carol", "key:x", decoder_sha256=SHA)
        with pytest.raises(ValueError, match="decoder_sha256"):
            reg.add("carol", "22222222", decoder_sha256="not-a-hash")
        with pytest.raises(ValueError, match="width"):
            reg.add("carol", "22222222", decoder_sha256=SHA, width=0)
        with pytest.raises(ValueError, match="non-empty"):
            reg.add("  ", "22222222", decoder_sha256=SHA)
        # all or nothing: the duplicate in the middle of a batch leaves nothing behind
        with pytest.raises(ValueError, match="already registered"):
            reg.add_many([dict(label="dave", message="33333333", decoder_sha256=SHA),
                          dict(label="alice", message="44444444", decoder_sha256=SHA)])
        assert [m.label for m in reg.list()] == ["alice", "bob"]
        ids = reg.add_many([dict(label=f"user{i}", message=f"{i:08x}", decoder_sha256=SHA) for i in range(5)])
        assert [reg.get(i).label for i in ids] == [f"user{i}" for i in range(5)]


def test_new_registry_is_private(tmp_path) -> None:
    old = os.umask(0)  # even with a permissive umask
    try:
        path = tmp_path / "new" / "dir" / "reg.sqlite"
        open_registry(path).close()
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o600
    assert path.parent.stat().st_mode & 0o777 == 0o700


def test_default_location(monkeypatch, tmp_path) -> None:
    monkeypatch.setenv("GSW_REGISTRY", str(tmp_path / "env.sqlite"))
    assert default_registry_path() == tmp_path / "env.sqlite"
    monkeypatch.delenv("GSW_REGISTRY")
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert default_registry_path() == tmp_path / "xdg" / "gsw" / "registry.sqlite"
    monkeypatch.delenv("XDG_DATA_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_registry_path() == tmp_path / "home" / ".local" / "share" / "gsw" / "registry.sqlite"
    with open_registry() as reg:
        assert reg.path == default_registry_path() and reg.path.is_file()


def test_missing_file_without_create(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="no mark registry at .*absent.sqlite"):
        open_registry(tmp_path / "absent.sqlite", create=False)
    assert not (tmp_path / "absent.sqlite").exists()


_WRITER = """
import os, sys, time
import gsw.mark.message  # the heavy imports before the start signal, so the two writers overlap
from gsw.registry import open_registry
print("ready", flush=True)
while not os.path.exists(sys.argv[3]):
    time.sleep(0.005)
with open_registry(sys.argv[1]) as reg:
    for i in range(20):
        reg.add(f"{sys.argv[2]}-{i}", f"{sys.argv[2]}{i:07x}", decoder_sha256="ab" * 32)
"""


def test_two_processes_writing_at_once_both_land(tmp_path) -> None:
    path, go = tmp_path / "reg.sqlite", tmp_path / "go"
    open_registry(path).close()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    procs = [subprocess.Popen([sys.executable, "-c", _WRITER, str(path), tag, str(go)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for tag in ("a", "b")]
    for p in procs:
        assert p.stdout.readline().strip() == "ready", p.communicate()[1]
    go.touch()  # both start writing now
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    with open_registry(path) as reg:
        marks = reg.list()
    assert len(marks) == 40 and len({m.id for m in marks}) == 40
    assert {m.label for m in marks} == {f"{t}-{i}" for t in "ab" for i in range(20)}


def test_not_a_database_names_the_file(tmp_path) -> None:
    path = tmp_path / "notes.sqlite"
    path.write_text("these are not the marks you are looking for\n" * 100)
    with pytest.raises(RegistryError, match=f"{path}.*not a gsw registry"):
        open_registry(path)
    assert path.read_text().startswith("these are not")  # never overwritten


def test_foreign_or_broken_databases_are_refused(tmp_path) -> None:
    foreign = tmp_path / "foreign.sqlite"
    with sqlite3.connect(foreign) as conn:
        conn.execute("CREATE TABLE photos (x)")
    with pytest.raises(RegistryError, match=f"{foreign} is an SQLite database but not a gsw registry"):
        open_registry(foreign)
    no_table = tmp_path / "no_table.sqlite"
    with sqlite3.connect(no_table) as conn:
        conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
    with pytest.raises(RegistryError, match=f"{no_table} is corrupt: table 'marks' is missing"):
        open_registry(no_table)


def test_newer_schema_is_refused(tmp_path) -> None:
    path = tmp_path / "future.sqlite"
    open_registry(path).close()
    with sqlite3.connect(path) as conn:
        conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(RegistryError, match=f"{path} was written by a newer gsw.*upgrade gsw"):
        open_registry(path)


def test_a_held_lock_gives_a_clear_error_within_the_timeout(tmp_path) -> None:
    path = tmp_path / "reg.sqlite"
    reg = open_registry(path, timeout=0.3)
    reg.add("alice", "0123abcd", decoder_sha256=SHA)
    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("BEGIN EXCLUSIVE")
    try:
        for action in (lambda: open_registry(path, timeout=0.3), reg.list,
                       lambda: reg.add("bob", "11111111", decoder_sha256=SHA)):
            start = time.monotonic()
            with pytest.raises(RegistryError, match=f"{path} is locked by another process"):
                action()
            assert time.monotonic() - start < 10.0  # bounded: not a hang
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    reg.add("bob", "11111111", decoder_sha256=SHA)  # usable again once the lock is gone
    assert [m.label for m in reg.list()] == ["alice", "bob"]
    reg.close()


def test_model_hashes(tmp_path) -> None:
    g = random_model(50)
    assert hash_gaussians(g) == hash_gaussians(g.detach().clone())
    assert hash_gaussians(g).startswith("gaussians-sha256:") and len(hash_gaussians(g)) == 17 + 64
    changed = g.detach().clone()
    changed.sh[3, 0, 1] += 1e-3
    assert hash_gaussians(changed) != hash_gaussians(g)
    f = tmp_path / "m.bin"
    f.write_bytes(b"model")
    assert hash_model_file(f) == "sha256:" + hashlib.sha256(b"model").hexdigest()


def test_shipped_decoder_sha256_matches_the_manifest() -> None:
    import json

    from gsw.decoder.zoo import WEIGHTS_DIR

    manifest = json.loads((WEIGHTS_DIR / "manifest.json").read_text())["files"]
    for k in (32, 48, 64):
        assert shipped_decoder_sha256(k) == manifest[f"hidden_k{k}.pt"]["sha256"]
    with pytest.raises(RuntimeError, match="no shipped decoder for 40 bits"):
        shipped_decoder_sha256(40)


_SCHEMA_1 = """CREATE TABLE marks (
    id INTEGER PRIMARY KEY AUTOINCREMENT, label TEXT NOT NULL UNIQUE, message_hex TEXT NOT NULL,
    num_bits INTEGER NOT NULL CHECK (num_bits > 0), decoder_sha256 TEXT NOT NULL, model_hash TEXT, width INTEGER,
    height INTEGER, background TEXT, created TEXT NOT NULL, gsw_version TEXT NOT NULL,
    UNIQUE (decoder_sha256, message_hex))"""


def _schema_1_file(path: Path) -> Path:
    """A registry as gsw wrote it before the message origin existed (schema 1), with one mark."""
    with sqlite3.connect(path) as conn:
        conn.execute(_SCHEMA_1)
        conn.execute("INSERT INTO marks (label, message_hex, num_bits, decoder_sha256, created, gsw_version) "
                     "VALUES ('old', '0123abcd', 32, ?, 't', '0.1')", (SHA,))
        conn.execute("PRAGMA user_version = 1")
    return path


def test_message_origin_round_trip_and_errors(tmp_path) -> None:
    with open_registry(tmp_path / "reg.sqlite") as reg:
        reg.add("typed", "0123abcd", decoder_sha256=SHA)  # the conservative default
        reg.add("drawn", "89abcdef", decoder_sha256=SHA, origin="random")
        assert [m.origin for m in reg.list()] == ["chosen", "random"]
        assert reg.get("drawn").to_dict()["origin"] == "random"
        with pytest.raises(ValueError, match="origin must be one of random, chosen, got 'typed'"):
            reg.add("bad", "00000000", decoder_sha256=SHA, origin="typed")
        assert len(reg) == 2
    from gsw.registry import record_mark

    key = record_mark(tmp_path / "reg.sqlite", "keyed", "key:s3cret", num_bits=32, decoder_sha256=SHA)
    hexed = record_mark(tmp_path / "reg.sqlite", "hexed", "fedcba98", decoder_sha256=SHA)
    assert (key.origin, hexed.origin) == ("random", "chosen")


def test_schema_1_registry_is_migrated_with_chosen_origins(tmp_path) -> None:
    path = _schema_1_file(tmp_path / "v1.sqlite")
    with open_registry(path) as reg:
        (old,) = reg.list()
        assert old.label == "old" and old.origin == "chosen" and old.message_hex == "0123abcd"
        reg.add("new", "89abcdef", decoder_sha256=SHA, origin="random")
    with sqlite3.connect(path) as conn:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION == 2
        rows = conn.execute("SELECT label, origin FROM marks ORDER BY id").fetchall()
    assert rows == [("old", "chosen"), ("new", "random")]
    with open_registry(path) as reg:  # a migrated file opens as is
        assert [m.origin for m in reg.list()] == ["chosen", "random"]


def test_schema_1_registry_that_cannot_be_written_is_read_as_chosen(tmp_path, monkeypatch) -> None:
    from gsw.registry import Registry

    path = _schema_1_file(tmp_path / "v1.sqlite")

    def readonly(self, doing):
        raise RegistryError(f"registry {self.path} cannot be written (attempt to write a readonly database)")

    monkeypatch.setattr(Registry, "_write", readonly)
    with open_registry(path) as reg:
        assert [(m.label, m.origin) for m in reg.list()] == [("old", "chosen")] and reg.get("old").origin == "chosen"
    with sqlite3.connect(path) as conn:
        assert conn.execute("PRAGMA user_version").fetchone()[0] == 1  # left as it was


def test_unknown_older_schema_is_refused(tmp_path) -> None:
    path = tmp_path / "odd.sqlite"
    with sqlite3.connect(path) as conn:
        conn.execute(_SCHEMA_1)
        conn.execute("PRAGMA user_version = -3")
    with pytest.raises(RegistryError, match="unknown schema version -3"):
        open_registry(path)
