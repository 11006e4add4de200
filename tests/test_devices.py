"""Device resolution: names, CUDA availability, and CPU threads fixed once so results do not follow the load."""

import pytest
import torch

from steering_core import devices


def test_resolving_a_device_fixes_the_cpu_threads_once_at_torchs_count(monkeypatch):
    calls = []
    monkeypatch.setattr(torch, "set_num_threads", calls.append)
    devices.fix_cpu_threads.cache_clear()
    try:
        assert devices.resolve_device("cpu") == torch.device("cpu")
        assert devices.resolve_device(None).type in ("cpu", "cuda")
        assert calls == [torch.get_num_threads()]  # once per process, the count unchanged (MKL_DYNAMIC off)
    finally:
        devices.fix_cpu_threads.cache_clear()


def test_bad_device_names_are_one_clear_error():
    with pytest.raises(ValueError, match="device 'gpu0' is not a torch device; expected cpu, cuda, cuda:N or auto"):
        devices.resolve_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available here"):
            devices.resolve_device("cuda")
