"""The registry of issued marks: which recipient got which message, in one SQLite file.

A studio hands out one watermarked copy per recipient; the registry remembers, for each copy, the
recipient's label, the secret message, the decoder that reads it (its sha256), the model that carries it
and how it was rendered. ``gsw identify`` tests a leaked image or video against every registered mark
(:func:`gsw.mark.identify.identify`).

The registry is the **only** place messages live: they are never written into a model folder. It is a
secret, so a new registry file is created with mode 0600 (and its folder, when created, 0700).

Location: ``$GSW_REGISTRY`` if set, else ``$XDG_DATA_HOME/gsw/registry.sqlite`` (``XDG_DATA_HOME``
defaulting to ``~/.local/share``); every command takes ``--registry FILE`` instead
(:func:`default_registry_path`).

Storage: one table ``marks``; the schema version is SQLite's ``PRAGMA user_version``
(:data:`SCHEMA_VERSION`): a file from a newer gsw is refused rather than misread.  Schema 2 added each
message's ``origin`` (:data:`gsw.stats.ORIGINS`); a schema-1 file is migrated when opened (or, read-only,
read as if it were), its marks ``"chosen"``: the conservative test, since nothing says how they were made. Every write is one
``BEGIN IMMEDIATE`` transaction, so concurrent writers (several processes) queue instead of losing rows;
a lock held longer than the busy timeout raises :class:`RegistryError` instead of hanging.

Example:
    >>> import tempfile, os
    >>> path = os.path.join(tempfile.mkdtemp(), "marks.sqlite")
    >>> with open_registry(path) as reg:
    ...     mark_id = reg.add("alice", "0123abcd", decoder_sha256="0" * 64)
    ...     reg.get("alice").id == mark_id, reg.get(mark_id).num_bits
    (True, 32)
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
import sqlite3
from collections.abc import Iterable, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

if TYPE_CHECKING:  # pragma: no cover
    from torch import Tensor, nn

    from gsw.gaussians import Gaussians
    from gsw.mark.message import MessageLike

__all__ = ["SCHEMA_VERSION", "BUSY_TIMEOUT_S", "Mark", "Registry", "RegistryError", "UnknownMarkError",
           "default_registry_path", "open_registry", "hash_gaussians", "hash_model_file",
           "record_mark", "shipped_decoder_sha256", "mark_decoder_sha256"]

#: Version of the table layout, stored as ``PRAGMA user_version`` (2: the ``origin`` column).
SCHEMA_VERSION = 2
#: Seconds a read or write waits for another process's lock before :class:`RegistryError`.
BUSY_TIMEOUT_S = 10.0

_TABLE = "marks"
_COLUMNS = ("id", "label", "message_hex", "num_bits", "decoder_sha256", "model_hash", "width", "height",
            "background", "created", "gsw_version", "origin")
_ORIGIN_COLUMN = "origin TEXT NOT NULL DEFAULT 'chosen' CHECK (origin IN ('random', 'chosen'))"
_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS {_TABLE} (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    label TEXT NOT NULL UNIQUE,
    message_hex TEXT NOT NULL,
    num_bits INTEGER NOT NULL CHECK (num_bits > 0),
    decoder_sha256 TEXT NOT NULL,
    model_hash TEXT,
    width INTEGER,
    height INTEGER,
    background TEXT,
    created TEXT NOT NULL,
    gsw_version TEXT NOT NULL,
    {_ORIGIN_COLUMN},
    UNIQUE (decoder_sha256, message_hex)
)"""
_LABEL_MAX = 200


class RegistryError(RuntimeError):
    """The registry file cannot be used: not a registry, corrupt, from a newer gsw, locked, unwritable."""


class UnknownMarkError(RegistryError, LookupError):
    """No mark has the requested id or label."""


@dataclass(frozen=True)
class Mark:
    """One issued mark (a row of the registry).

    Attributes:
        id: registry id (positive, never reused).
        label: the recipient (unique; never all digits, so ids and labels cannot be confused).
        message_hex: the secret message (``num_bits / 4`` hex digits, most significant bit first); kept out
            of ``repr`` and of :meth:`to_dict` unless asked for.
        num_bits: message length.
        decoder_sha256: sha256 of the decoder weight file that reads the message.
        model_hash: hash of the watermarked model (:func:`hash_model_file` or :func:`hash_gaussians`), or None.
        width, height: embedding (render) resolution in pixels, or None.
        background: render background RGB in [0, 1], or None.
        created: UTC time of registration, ISO 8601.
        gsw_version: gsw version that registered it.
        origin: ``"random"`` (gsw's secret messages, ``key:``) or ``"chosen"`` (:data:`gsw.stats.ORIGINS`).
    """

    id: int
    label: str
    message_hex: str = field(repr=False)
    num_bits: int
    decoder_sha256: str
    model_hash: str | None
    width: int | None
    height: int | None
    background: tuple[float, float, float] | None
    created: str
    gsw_version: str
    origin: str = "chosen"

    @property
    def message(self) -> Tensor:
        """[num_bits] float 0/1 tensor of the message."""
        from gsw.mark.message import message_from_hex

        return message_from_hex(self.message_hex, self.num_bits)

    def to_dict(self, show_secret: bool = False) -> dict[str, Any]:
        """JSON-ready fields; ``message_hex`` only with ``show_secret``."""
        out = {name: getattr(self, name) for name in _COLUMNS if name != "message_hex" or show_secret}
        out["background"] = None if self.background is None else list(self.background)
        return out


def default_registry_path() -> Path:
    """``$GSW_REGISTRY``, else ``$XDG_DATA_HOME/gsw/registry.sqlite`` (``~/.local/share/gsw/...``)."""
    env = os.environ.get("GSW_REGISTRY")
    if env:
        return Path(env).expanduser()
    data_home = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(data_home).expanduser() / "gsw" / "registry.sqlite"


def hash_model_file(path: str | os.PathLike) -> str:
    """``"sha256:<hex>"`` of a model file's bytes (e.g. the watermarked ``point_cloud.ply``)."""
    from gsw.decoder.zoo import sha256_file

    return f"sha256:{sha256_file(path)}"


def hash_gaussians(gaussians: Gaussians) -> str:
    """``"gaussians-sha256:<hex>"``: a canonical hash of a model's tensors, independent of the file format.

    Hashes, per field (means, log_scales, quats, opacity_logits, sh, in this order), its name, shape and
    float32 little-endian values; the same model saved as PLY or ``.splat`` at full precision, or held
    on another device, hashes alike."""
    h = hashlib.sha256()
    for name in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        t = getattr(gaussians, name).detach().float().cpu().contiguous()
        h.update(f"{name}:{list(t.shape)};".encode())
        h.update(t.numpy().astype("<f4", copy=False).tobytes())
    return f"gaussians-sha256:{h.hexdigest()}"


def shipped_decoder_sha256(num_bits: int) -> str:
    """sha256 of the shipped decoder file for ``num_bits`` (what :func:`gsw.decoder.load_decoder` loads)."""
    from gsw.decoder.zoo import AVAILABLE_BITS, WeightsError, sha256_file, weights_path

    if num_bits not in AVAILABLE_BITS:
        raise WeightsError(f"no shipped decoder for {num_bits} bits (available: {AVAILABLE_BITS})")
    return sha256_file(weights_path(num_bits))


def mark_decoder_sha256(num_bits: int, decoder: nn.Module | None) -> str:
    """What a registry records as the decoder of a mark embedded through ``decoder``: the shipped weight file's
    sha256 for None (:func:`shipped_decoder_sha256`), else the decoder's weights fingerprint
    (:func:`gsw.decoder.null.decoder_fingerprint`); for ``KleinReadout(load_decoder(k))`` that is
    :func:`gsw.decoder.readout.shipped_klein_fingerprint`, by which ``gsw identify`` / ``gsw scan`` recognise its
    marks."""
    if decoder is None:
        return shipped_decoder_sha256(num_bits)
    from gsw.decoder.null import decoder_fingerprint

    return decoder_fingerprint(decoder)


def _check_label(label: str) -> str:
    if not isinstance(label, str) or not label.strip():
        raise ValueError("a mark's recipient label must be a non-empty string")
    label = label.strip()
    if label.isdigit():
        raise ValueError(f"label {label!r} is all digits, which reads as a registry id; add a letter")
    if len(label) > _LABEL_MAX or any(ord(c) < 32 or ord(c) == 127 for c in label):
        raise ValueError(f"label {label!r} must be at most {_LABEL_MAX} printable characters")
    return label


def _message_hex(message: MessageLike, num_bits: int | None) -> tuple[str, int]:
    """(hex, bit length) of a message given as hex, ``key:<secret>``, bits or a tensor."""
    from gsw.mark.detect import message_num_bits
    from gsw.mark.message import as_message, message_to_hex

    if message is None:
        raise ValueError("a mark needs a message (hex, key:<secret> or bits)")
    num_bits = message_num_bits(message) if num_bits is None else num_bits
    return message_to_hex(as_message(message, num_bits)), num_bits


def _row(label: str, message: MessageLike, *, num_bits: int | None = None, decoder_sha256: str,
         model_hash: str | None = None, width: int | None = None, height: int | None = None,
         background: Sequence[float] | None = None, origin: str = "chosen") -> tuple[Any, ...]:
    """The checked table row (without id) of :meth:`Registry.add`'s arguments."""
    from gsw import __version__
    from gsw.stats import check_origin

    check_origin(origin)
    label = _check_label(label)
    hex_message, k = _message_hex(message, num_bits)
    if not isinstance(decoder_sha256, str) or not re.fullmatch(r"[0-9a-f]{64}", decoder_sha256):
        raise ValueError(f"decoder_sha256 must be 64 lowercase hex digits, got {decoder_sha256!r}")
    for name, value in (("width", width), ("height", height)):
        if value is not None and (not isinstance(value, int) or value <= 0):
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    bg = None
    if background is not None:
        values = [float(v) for v in background]
        if len(values) != 3:
            raise ValueError(f"background must be 3 values (RGB), got {len(values)}")
        bg = json.dumps(values)
    created = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    return (label, hex_message, k, decoder_sha256, model_hash, width, height, bg, created, __version__, origin)


def _row_to_mark(row: Sequence[Any]) -> Mark:
    values = dict(zip(_COLUMNS, row))
    bg = values["background"]
    values["background"] = None if bg is None else tuple(float(v) for v in json.loads(bg))
    return Mark(**values)


def _create_private(path: Path) -> None:
    """Creates an empty file with mode 0600 (its folder, if missing, 0700); an existing file is kept."""
    if not path.parent.exists():
        path.parent.mkdir(parents=True, mode=0o700)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return
    os.fchmod(fd, 0o600)  # whatever the umask
    os.close(fd)


class Registry:
    """An open registry (use :func:`open_registry`). A context manager; not shared between threads."""

    def __init__(self, path: Path, conn: sqlite3.Connection, timeout: float) -> None:
        self.path = path
        self._conn = conn
        self._timeout = timeout
        self._select = ", ".join(_COLUMNS)  # a schema-1 file that cannot be migrated reads origin as "chosen"

    # -- plumbing ---------------------------------------------------------------------------------------
    @contextmanager
    def _errors(self, doing: str) -> Iterator[None]:
        """Turns SQLite errors into a :class:`RegistryError` naming the file."""
        try:
            yield
        except sqlite3.IntegrityError:
            raise
        except sqlite3.OperationalError as err:
            text = str(err)
            if "locked" in text or "busy" in text:
                raise RegistryError(f"registry {self.path} is locked by another process (waited "
                                    f"{self._timeout:g} s while {doing}); try again") from None
            if "readonly" in text or "unable to open" in text:
                raise RegistryError(f"registry {self.path} cannot be written ({text})") from None
            raise RegistryError(f"registry {self.path}: {doing} failed: {text}") from None
        except sqlite3.DatabaseError as err:
            raise RegistryError(f"registry {self.path} is not a gsw registry (not an SQLite database, or "
                                f"corrupt: {err})") from None

    @contextmanager
    def _write(self, doing: str) -> Iterator[sqlite3.Connection]:
        """One ``BEGIN IMMEDIATE`` transaction: committed on success, rolled back on any error."""
        with self._errors(doing):
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                yield self._conn
                self._conn.execute("COMMIT")  # may wait for readers (busy timeout)
            except BaseException:
                if self._conn.in_transaction:
                    self._conn.execute("ROLLBACK")
                raise

    def _initialise(self) -> None:
        """Creates the table in a new file; checks the schema version and table of an existing one."""
        with self._errors("reading the schema"):
            version = self._conn.execute("PRAGMA user_version").fetchone()[0]
        if version == 0:
            with self._write("creating the table") as conn:
                version = conn.execute("PRAGMA user_version").fetchone()[0]  # another process may have won
                tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
                if version == 0 and tables - {"sqlite_sequence"}:
                    raise RegistryError(f"{self.path} is an SQLite database but not a gsw registry (tables: "
                                        f"{', '.join(sorted(tables))})")
                if version == 0:
                    conn.execute(_SCHEMA)
                    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                    version = SCHEMA_VERSION
        if version > SCHEMA_VERSION:
            raise RegistryError(f"registry {self.path} was written by a newer gsw (schema {version}; this gsw "
                                f"reads up to {SCHEMA_VERSION}): upgrade gsw")
        if version == 1:
            version = self._migrate_from_1()
        if version != SCHEMA_VERSION:
            raise RegistryError(f"registry {self.path} has an unknown schema version {version}")
        with self._errors("reading the schema"):
            cols = [r[1] for r in self._conn.execute(f"PRAGMA table_info({_TABLE})")]
        legacy = "'chosen' AS origin" in self._select  # an unmigrated schema-1 file has no origin column
        if missing := [c for c in _COLUMNS if c not in cols and not (legacy and c == "origin")]:
            what = f"table {_TABLE!r} is missing" if not cols else f"table {_TABLE!r} lacks {', '.join(missing)}"
            raise RegistryError(f"registry {self.path} is corrupt: {what}")

    def _migrate_from_1(self) -> int:
        """Schema 1 -> 2 in one transaction (a read-only file: origin read as "chosen"). Returns the version."""
        try:
            with self._write("migrating schema 1 to 2") as conn:
                version = conn.execute("PRAGMA user_version").fetchone()[0]  # another process may have done it
                if version == 1:
                    conn.execute(f"ALTER TABLE {_TABLE} ADD COLUMN {_ORIGIN_COLUMN}")
                    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                    version = SCHEMA_VERSION
            return version
        except RegistryError as err:
            if "cannot be written" not in str(err):
                raise
        self._select = ", ".join(c if c != "origin" else "'chosen' AS origin" for c in _COLUMNS)
        return SCHEMA_VERSION

    # -- API --------------------------------------------------------------------------------------------
    def add(self, label: str, message: MessageLike, *, num_bits: int | None = None, decoder_sha256: str,
            model_hash: str | None = None, width: int | None = None, height: int | None = None,
            background: Sequence[float] | None = None, origin: str = "chosen") -> int:
        """Registers a mark in one transaction and returns its id.

        Args:
            label: the recipient (unique, not all digits).
            message: hex (``num_bits / 4`` digits), ``key:<secret>``, or [k] 0/1 bits / tensor.
            num_bits: message length (inferred from hex or bits; required for a key).
            decoder_sha256: sha256 of the decoder file that reads it (:func:`shipped_decoder_sha256`).
            model_hash: :func:`hash_model_file` / :func:`hash_gaussians` of the watermarked model.
            width, height: embedding resolution in pixels.
            background: render background RGB.
            origin: ``"random"`` (drawn at random: gsw's messages, ``key:``) or ``"chosen"`` (default).

        Raises:
            ValueError: bad label, message or origin, a label already registered, or the same message already
                issued for this decoder (two recipients would be indistinguishable).
            RegistryError: the file cannot be written (locked past the busy timeout, read-only, corrupt).
        """
        return self.add_many([dict(label=label, message=message, num_bits=num_bits, decoder_sha256=decoder_sha256,
                                   model_hash=model_hash, width=width, height=height, background=background,
                                   origin=origin)])[0]

    def add_many(self, marks: Iterable[Mapping[str, Any]]) -> list[int]:
        """Registers several marks in ONE transaction (all or none); returns their ids in order.

        Args:
            marks: mappings of :meth:`add`'s arguments (``label``, ``message``, ``decoder_sha256``, ...).

        Raises:
            ValueError, RegistryError: as :meth:`add` (nothing is written then).
        """
        rows = [_row(**m) for m in marks]
        insert = f"INSERT INTO {_TABLE} ({', '.join(_COLUMNS[1:])}) VALUES ({', '.join('?' * (len(_COLUMNS) - 1))})"
        try:
            with self._write("adding marks") as conn:
                return [int(conn.execute(insert, row).lastrowid) for row in rows]
        except sqlite3.IntegrityError as err:
            if "label" in str(err):
                raise ValueError(f"a label is already registered in {self.path} ({err})") from None
            raise ValueError(f"a message is already issued for the same decoder in {self.path} (two recipients "
                             "would be indistinguishable); use another message") from None

    def list(self, *, num_bits: int | None = None) -> list[Mark]:
        """Every mark (or those of one message length), by id."""
        query = f"SELECT {self._select} FROM {_TABLE}"
        args: tuple[Any, ...] = ()
        if num_bits is not None:
            query, args = query + " WHERE num_bits = ?", (int(num_bits),)
        with self._errors("listing marks"):
            rows = self._conn.execute(query + " ORDER BY id", args).fetchall()
        return [_row_to_mark(r) for r in rows]

    def of_model(self, *hashes: str) -> list[Mark]:
        """The marks recorded for a model with any of ``hashes`` (its :func:`hash_gaussians` and / or the
        :func:`hash_model_file` of its file), by id."""
        if not hashes:
            return []
        query = f"SELECT {self._select} FROM {_TABLE} WHERE model_hash IN ({', '.join('?' * len(hashes))}) ORDER BY id"
        with self._errors("looking up a model's marks"):
            rows = self._conn.execute(query, tuple(hashes)).fetchall()
        return [_row_to_mark(r) for r in rows]

    def get(self, ref: int | str) -> Mark:
        """The mark with id ``ref`` (an int or a string of digits) or label ``ref``.

        Raises:
            UnknownMarkError: no such id or label.
        """
        by_id = isinstance(ref, int) or (isinstance(ref, str) and ref.strip().isdigit())
        column, value = ("id", int(ref)) if by_id else ("label", str(ref).strip())
        with self._errors("reading a mark"):
            row = self._conn.execute(f"SELECT {self._select} FROM {_TABLE} WHERE {column} = ?",
                                     (value,)).fetchone()
        if row is None:
            raise UnknownMarkError(f"no mark with {column} {value!r} in registry {self.path}")
        return _row_to_mark(row)

    def __len__(self) -> int:
        with self._errors("counting marks"):
            return int(self._conn.execute(f"SELECT COUNT(*) FROM {_TABLE}").fetchone()[0])

    def close(self) -> None:
        """Closes the connection (idempotent)."""
        self._conn.close()

    def __enter__(self) -> Registry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Registry({str(self.path)!r})"


def open_registry(path: str | os.PathLike | None = None, *, create: bool = True,
                  timeout: float = BUSY_TIMEOUT_S) -> Registry:
    """Opens (by default creating, mode 0600) a registry file.

    Args:
        path: the file; default :func:`default_registry_path`.
        create: create a missing file; False raises FileNotFoundError instead (read-only commands).
        timeout: seconds to wait for another process's lock before raising :class:`RegistryError`.

    Returns:
        A :class:`Registry` (close it, or use it as a context manager).

    Raises:
        FileNotFoundError: ``create`` is False and the file does not exist.
        RegistryError: not an SQLite file, no ``marks`` table, a newer schema, locked past ``timeout``,
            or not readable.
    """
    path = Path(path).expanduser() if path is not None else default_registry_path()
    if path.exists() and not path.is_file():
        raise RegistryError(f"registry {path} is not a file")
    if not path.exists():
        if not create:
            raise FileNotFoundError(f"no mark registry at {path} (marks are recorded when issued; pass "
                                    "--registry FILE or set GSW_REGISTRY)")
        try:
            _create_private(path)
        except OSError as err:
            raise RegistryError(f"cannot create registry {path}: {err}") from None
    try:
        conn = sqlite3.connect(path, timeout=timeout, isolation_level=None)
    except sqlite3.Error as err:
        raise RegistryError(f"cannot open registry {path}: {err}") from None
    registry = Registry(path, conn, timeout)
    try:
        registry._initialise()
    except BaseException:
        conn.close()
        raise
    return registry


def record_mark(registry: Registry | str | os.PathLike | None, label: str, message: MessageLike, *,
                num_bits: int | None = None, gaussians: Gaussians | None = None, model_hash: str | None = None,
                size: tuple[int, int] | None = None, background: Sequence[float] | None = None,
                decoder_sha256: str | None = None, origin: str | None = None) -> Mark:
    """Records an issued mark (what ``gsw embed --label`` / ``gsw embed-image --label`` do), in one transaction.

    Example (``res`` from :func:`gsw.embed`, cameras of one size)::

        record_mark("marks.sqlite", "alice", res.message, gaussians=res.gaussians,
                    size=(cams[0].width, cams[0].height), background=(1.0, 1.0, 1.0), origin="random")

    Args:
        registry: an open :class:`Registry`, or its file (None: :func:`default_registry_path`), opened
            (created with mode 0600 if missing) and closed here.
        label: the recipient.
        message: the embedded message (bits, hex or ``key:<secret>``).
        num_bits: message length (inferred from bits or hex).
        gaussians: the watermarked model; its :func:`hash_gaussians` is recorded (or pass ``model_hash``).
        model_hash: the model's hash, when ``gaussians`` is not given.
        size: ``(width, height)`` of the embedding renders (None when they had several sizes).
        background: render background RGB.
        decoder_sha256: the decoder file's sha256; default: the shipped ``num_bits`` decoder's.
        origin: ``"random"`` or ``"chosen"``; default ``"random"`` for ``key:<secret>``, else ``"chosen"``.

    Returns:
        The :class:`Mark` as stored.

    Raises:
        ValueError: bad label / message / size, a label or (decoder, message) already registered.
        RegistryError: the registry cannot be opened or written.
    """
    _, k = _message_hex(message, num_bits)
    if gaussians is not None:
        model_hash = hash_gaussians(gaussians)
    width, height = (None, None) if size is None else (int(size[0]), int(size[1]))
    if origin is None:
        origin = "random" if isinstance(message, str) and message.startswith("key:") else "chosen"
    fields = dict(num_bits=k, decoder_sha256=decoder_sha256 or shipped_decoder_sha256(k), model_hash=model_hash,
                  width=width, height=height, background=background, origin=origin)
    if isinstance(registry, Registry):
        return registry.get(registry.add(label, message, **fields))
    with open_registry(registry) as reg:
        return reg.get(reg.add(label, message, **fields))
