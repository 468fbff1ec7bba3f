"""Shared fixtures: the device matrix (cpu always, cuda when Warp sees a GPU) and small scenes."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

sys.path.insert(0, str(Path(__file__).parent))  # tests/reference.py

import tg_gpudrive  # noqa: F401  (sets Warp's log level)
import tg_gpudrive.config as _config

if not _config.REPO_CONFIGS.is_dir():  # the package installed apart from the checkout: the checkout's configs
    _config.REPO_CONFIGS = Path(__file__).resolve().parent.parent / "configs"

wp.init()

DATA = Path(__file__).parent / "data"
WOMD_FILES = sorted(DATA.glob("womd_*.json"))


def _cuda_available() -> bool:
    try:
        return wp.is_cuda_available()
    except Exception:  # pragma: no cover - driver probing failed
        return False


DEVICES = [
    "cpu",
    pytest.param("cuda:0", marks=pytest.mark.skipif(not _cuda_available(), reason="no CUDA device")),
]


@pytest.fixture(params=DEVICES)
def device(request):
    return request.param


@pytest.fixture(autouse=True)
def _matmul_precision_of_its_own():
    """Each test starts from torch's float32 matmuls: a Trainer turns TF32 on for the whole process, and a later
    test's comparison with an eager float32 reference on the GPU would read it."""
    import torch

    tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32 = tf32


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
