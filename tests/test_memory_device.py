"""The memory check holds a CUDA run against the card's free memory (faked here: no GPU needed)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from dvsland.config import ConfigError, load_config
from dvsland.config.validate import check_memory, device_free_bytes, memory_limit_bytes


def _cuda_cfg():
    cfg = load_config("paper")
    return replace(cfg, simulation=replace(cfg.simulation, device="cuda:0"))


def test_cpu_has_no_device_limit():
    assert device_free_bytes("cpu") is None
    cfg = load_config("paper")
    assert memory_limit_bytes(cfg) > 2 ** 30


def test_cuda_limit_is_the_cards_free_memory(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (2.0 * 2 ** 30, 80.0 * 2 ** 30))
    cfg = _cuda_cfg()
    assert device_free_bytes("cuda:0") == 2.0 * 2 ** 30
    assert memory_limit_bytes(cfg) == pytest.approx(0.9 * 2.0 * 2 ** 30)
    big = replace(cfg, simulation=replace(cfg.simulation, n_seeds=2000))
    with pytest.raises(ConfigError, match=r"GiB free on cuda:0"):
        check_memory(big)
    fixed = replace(big, simulation=replace(big.simulation, max_memory_gb=10000.0))
    check_memory(fixed)  # an explicit limit wins over the card's


def test_cuda_unavailable_falls_back_to_host(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert device_free_bytes("cuda") is None
    assert memory_limit_bytes(_cuda_cfg()) == memory_limit_bytes(load_config("paper"))
