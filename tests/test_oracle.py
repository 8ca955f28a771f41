"""The 'oracle' estimator: exact D, delay in steps, noise by seed, reset by mask, errors."""

from __future__ import annotations

import math

import pytest
import torch

from dvsland.estimators import Truth, get_estimator


def truth(k: int) -> Truth:
    z = torch.tensor([100.0, 200.0], dtype=torch.float64)
    v = torch.tensor([-(k + 1.0), -2.0], dtype=torch.float64)
    return Truth(z, v)


def test_exact_without_noise(device):
    est = get_estimator("oracle", 2, (8, 8), device)
    d = est.update(None, 100_000, truth(0))
    assert d.shape == (2,) and d.dtype == torch.float32 and d.device.type == device.type
    assert torch.allclose(d.cpu(), torch.tensor([-0.01, -0.01]))
    assert est.needs_events is False


def test_delay_steps():
    est = get_estimator("oracle", 2, (8, 8), delay_steps=2)
    out = [est.update(None, 0, truth(k))[0].item() for k in range(5)]
    assert math.isnan(out[0]) and math.isnan(out[1])
    assert out[2:] == pytest.approx([-0.01, -0.02, -0.03])


def test_reset_mask_touches_only_masked():
    est = get_estimator("oracle", 2, (8, 8), delay_steps=1)
    est.update(None, 0, truth(0))
    est.update(None, 0, truth(1))
    est.reset(torch.tensor([True, False]))
    d = est.update(None, 0, truth(2))
    assert math.isnan(d[0].item()) and d[1].item() == pytest.approx(-0.01)


def test_noise_is_seeded():
    a = get_estimator("oracle", 2, (8, 8), noise_abs=0.01, noise_rel=0.1, seed=3)
    b = get_estimator("oracle", 2, (8, 8), noise_abs=0.01, noise_rel=0.1, seed=3)
    da, db = a.update(None, 0, truth(0)), b.update(None, 0, truth(0))
    assert torch.equal(da, db) and not torch.allclose(da, torch.tensor([-0.01, -0.01]))


def test_errors():
    est = get_estimator("oracle", 2, (8, 8))
    with pytest.raises(ValueError, match="needs truth"):
        est.update(None, 0)
    with pytest.raises(ValueError, match="delay_steps"):
        get_estimator("oracle", 2, (8, 8), delay_steps=-1)
    with pytest.raises(ValueError, match="noise"):
        get_estimator("oracle", 2, (8, 8), noise_abs=-1.0)
    with pytest.raises(ValueError, match="mask"):
        est.reset(torch.tensor([True]))
