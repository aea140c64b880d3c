"""Test set-up: select glossrt's backend once (CPU unless GLOSSRT_DEVICE says otherwise)."""

import os

import pytest

os.environ.setdefault("GLOSSRT_DEVICE", "auto")

from glossrt import backend  # noqa: E402

VARIANT = backend.use()


def pytest_collection_modifyitems(config, items):
    if VARIANT == backend.GPU_VARIANT:
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)
