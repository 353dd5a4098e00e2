"""The output folder of a fingerprinting job and its resume rules.

Layout::

    DIR/.gsw-fingerprint.json        the job marker: scene hash, decoder sha256, message length (no secrets)
    DIR/<recipient>/                 an INRIA model folder (point_cloud/..., cameras.json, watermark.json)
    DIR/<recipient>/fingerprint.json the completion marker, written last (scene hash, model hash; no message)

A recipient's copy is written into a temporary sibling folder renamed into place, then registered
(:meth:`gsw.registry.Registry.add_many`), then marked complete. On a rerun a recipient is

- ``done`` (skipped): marker present, registered with the marker's model hash;
- ``finish``: registered with the hash of the model in its folder, marker missing (the run stopped between
  registration and marker): only the marker is written;
- ``todo``: neither registered nor complete; an old folder is replaced.

A recipient registered with another model (another job, another scene) is an error, as is a folder
of another scene or a folder that is not a fingerprint job's.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path
from typing import Any, Mapping, Sequence

from gsw._atomic import atomic_write

__all__ = ["JOB_FILE", "DONE_FILE", "JobFolder"]

JOB_FILE = ".gsw-fingerprint.json"
DONE_FILE = "fingerprint.json"
_FORMAT = 1


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: not a valid marker ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a valid marker (expected a JSON object)")
    return data


def _write_json(path: Path, data: Mapping[str, Any]) -> None:
    with atomic_write(path, "w") as f:
        json.dump(data, f, indent=2)
        f.write("\n")


class JobFolder:
    """The output folder of one scene's fingerprints.

    Args:
        path: the folder (created if missing).
        scene_hash: :func:`gsw.fingerprint.shared.scene_hash` of the job.
        decoder_sha256: the decoder the copies are read with.
        num_bits: message length.

    Raises:
        ValueError: the folder holds another scene's fingerprints, or is a non-empty folder that is not a
            fingerprint job's; nothing is written then.
    """

    def __init__(self, path: str | Path, *, scene_hash: str, decoder_sha256: str, num_bits: int) -> None:
        self.path = Path(path)
        self.scene_hash, self.decoder_sha256, self.num_bits = scene_hash, decoder_sha256, int(num_bits)
        marker = self.path / JOB_FILE
        if self.path.exists() and not self.path.is_dir():
            raise ValueError(f"output {self.path} exists and is not a folder")
        if marker.is_file():
            job = _read_json(marker)
            if job.get("scene_hash") != scene_hash:
                raise ValueError(f"output folder {self.path} holds fingerprints of another scene (another model, "
                                 f"cameras, images, bit length or embedding settings; {JOB_FILE}: "
                                 f"{job.get('scene_hash')}, this job: {scene_hash}); choose another --output")
            if job.get("decoder_sha256") != decoder_sha256 or job.get("num_bits") != self.num_bits:
                raise ValueError(f"output folder {self.path} holds fingerprints read by another decoder "
                                 f"({job.get('num_bits')} bits, {str(job.get('decoder_sha256'))[:12]}); this job: "
                                 f"{self.num_bits} bits, {decoder_sha256[:12]}")
        elif self.path.is_dir() and any(not p.name.startswith(".") for p in self.path.iterdir()):
            raise ValueError(f"output folder {self.path} is not empty and is not a fingerprint job's (no {JOB_FILE}); "
                             "choose a new or empty folder")

    def claim(self) -> None:
        """Creates the folder and writes the job marker (idempotent)."""
        self.path.mkdir(parents=True, exist_ok=True)
        if not (self.path / JOB_FILE).is_file():
            import gsw

            _write_json(self.path / JOB_FILE, dict(format=_FORMAT, scene_hash=self.scene_hash,
                                                   decoder_sha256=self.decoder_sha256, num_bits=self.num_bits,
                                                   gsw_version=gsw.__version__))

    def copy_path(self, name: str) -> Path:
        """The recipient's model folder."""
        return self.path / name

    def status(self, name: str, registered_hash: str | None, registered: bool) -> str:
        """``"done"``, ``"finish"`` or ``"todo"`` (module docstring).

        Args:
            name: the recipient.
            registered_hash: the model hash of its registry record (None: none recorded).
            registered: whether the registry holds a record for it.

        Raises:
            ValueError: registered with another model than the one in its folder (or with no folder).
        """
        folder = self.copy_path(name)
        done = folder / DONE_FILE
        if done.is_file():
            marker = _read_json(done)
            if marker.get("scene_hash") != self.scene_hash:
                raise ValueError(f"{done} belongs to another scene; remove {folder} to redo it")
            if registered and registered_hash == marker.get("model_hash"):
                return "done"
        if not registered:
            return "todo"
        if registered_hash is not None and folder.is_dir() and registered_hash == self.model_hash(name):
            return "finish"
        raise ValueError(f"recipient {name!r} is already registered with another model (not the copy in {folder}): "
                         "a name is issued once; use another name or another registry")

    def model_hash(self, name: str) -> str | None:
        """:func:`gsw.registry.hash_model_file` of the copy's PLY, or None when it has none."""
        from gsw.registry import hash_model_file

        plys = sorted(self.copy_path(name).glob("point_cloud/iteration_*/point_cloud.ply"))
        return hash_model_file(plys[-1]) if plys else None

    def write_copy(self, name: str, gaussians, cameras: Sequence, record: Mapping[str, Any]) -> str:
        """Writes the recipient's model folder atomically (replacing an unfinished one).

        Args:
            name: the recipient.
            gaussians: the watermarked model.
            cameras: the embedding views (``cameras.json``).
            record: the ``watermark.json`` content (no secrets).

        Returns:
            The model hash (:func:`gsw.registry.hash_model_file` of the PLY).
        """
        from gsw.cli.metadata import write_watermark_json
        from gsw.data import save_inria_model

        target = self.copy_path(name)
        tmp = Path(tempfile.mkdtemp(prefix=f".{name}.", suffix=".tmp", dir=self.path))
        try:
            save_inria_model(tmp, gaussians, cameras, iteration=0)
            write_watermark_json(tmp, record)
            if target.exists():
                old = self.path / f".{name}.old"
                shutil.rmtree(old, ignore_errors=True)
                target.rename(old)
                tmp.rename(target)
                shutil.rmtree(old, ignore_errors=True)
            else:
                tmp.rename(target)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        model_hash = self.model_hash(name)
        assert model_hash is not None
        return model_hash

    def mark_done(self, name: str, model_hash: str, mark_id: int) -> None:
        """Writes the completion marker, last (no message)."""
        _write_json(self.copy_path(name) / DONE_FILE,
                    dict(format=_FORMAT, recipient=name, scene_hash=self.scene_hash, model_hash=model_hash,
                         registry_id=int(mark_id), decoder_sha256=self.decoder_sha256, num_bits=self.num_bits))
