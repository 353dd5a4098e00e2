"""gsw.device: the cuDNN flag contexts (deterministic fine-tunes, the DWT's exact float32)."""

from __future__ import annotations

import pytest
import torch

from gsw.device import cudnn_flags, deterministic


def test_flags_are_set_inside_and_restored_after_an_error() -> None:
    cudnn = torch.backends.cudnn
    before = cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32
    with pytest.raises(KeyError):
        with cudnn_flags(deterministic=not before[0], allow_tf32=not before[2]):
            assert (cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32) == (not before[0], before[1],
                                                                                not before[2])
            raise KeyError("inside")
    assert (cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32) == before
    with deterministic():
        assert cudnn.deterministic and not cudnn.benchmark
    assert (cudnn.deterministic, cudnn.benchmark, cudnn.allow_tf32) == before
