"""Per-recipient fingerprints at scale: one scene, many recipients, each with their own message.

``gsw.fingerprint(model, cameras, recipients, output_dir, registry, ...)`` (:func:`~gsw.fingerprint.job.fingerprint`;
the module itself is callable) writes one watermarked copy per recipient, registers it, and resumes an
interrupted job. Modules: :mod:`~gsw.fingerprint.plan` (recipients file, messages),
:mod:`~gsw.fingerprint.shared` (the once-per-scene work), :mod:`~gsw.fingerprint.batched` (a pool of slots
fine-tuning several recipients together), :mod:`~gsw.fingerprint.stopping` (per-recipient early stopping),
:mod:`~gsw.fingerprint.store` (output folder, resume rules), :mod:`~gsw.fingerprint.run`
(in-process and Ray runners), :mod:`~gsw.fingerprint.scan` (identifying many images and videos at once).

Example:
    >>> import gsw                                                       # doctest: +SKIP
    >>> report = gsw.fingerprint(model, cameras, "recipients.csv", "copies", "marks.sqlite")  # doctest: +SKIP
    >>> report.names("embedded")                                         # doctest: +SKIP
    ['alice', 'bob']
"""

from __future__ import annotations

import sys
import types
from typing import Any

from gsw.fingerprint.job import FingerprintReport, RecipientReport, fingerprint
from gsw.fingerprint.plan import Recipient, read_recipients
from gsw.fingerprint.stopping import EarlyStop

__all__ = ["EarlyStop", "FingerprintReport", "Recipient", "RecipientReport", "fingerprint", "read_recipients"]


class _CallableModule(types.ModuleType):
    """Makes ``gsw.fingerprint(...)`` work whether ``gsw.fingerprint`` is this module or the function."""

    def __call__(self, *args: Any, **kwargs: Any) -> FingerprintReport:
        return fingerprint(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
