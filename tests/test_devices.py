"""warpbags.devices: the one check of --device values (train, view and sweep use it)."""

from __future__ import annotations

import pytest
import torch

from warpbags.devices import checked_device_name, torch_device
from warpbags.errors import WarpbagsError


def test_device_names_and_availability():
    assert torch_device("cpu") == torch.device("cpu")
    assert torch_device(None) == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert checked_device_name("cuda") == "cuda"  # the name alone, wherever the run will go
    with pytest.raises(WarpbagsError, match="--device must be cpu or cuda, got 'tpu'"):
        torch_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(WarpbagsError, match="no CUDA device is available"):
            torch_device("cuda")
