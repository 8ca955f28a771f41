"""Events -> per-pixel count images, the estimators' common first step."""

from __future__ import annotations

from typing import Any

import torch


def event_count(events: Any) -> int:
    """Number of events in ``events`` (an Events container, or None = 0)."""
    if events is None:
        return 0
    return int(events.b.numel())


def count_image(events: Any, batch_size: int, height: int, width: int, device: Any = "cpu",
                by_polarity: bool = False) -> torch.Tensor:
    """Count events per pixel (ON and OFF summed unless ``by_polarity``).

    Args:
        events: ``dvsland.events.Events`` with integer fields b, x, y (and p, int8 +-1), or None.
        batch_size, height, width: B, H, W.
        by_polarity: if True return (B, 2, H, W) (channel 0 = ON, 1 = OFF), else (B, H, W).

    Returns:
        float32 tensor on ``device``; events outside the sensor or the batch are ignored.
    """
    B, H, W = int(batch_size), int(height), int(width)
    shape = (B, 2, H, W) if by_polarity else (B, H, W)
    if events is None or events.b.numel() == 0:
        return torch.zeros(shape, dtype=torch.float32, device=device)
    b = events.b.to(device=device, dtype=torch.int64)
    x = events.x.to(device=device, dtype=torch.int64)
    y = events.y.to(device=device, dtype=torch.int64)
    ok = (b >= 0) & (b < B) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
    if by_polarity:
        ch = (events.p.to(device=device) < 0).to(torch.int64)
        lin = ((b * 2 + ch) * H + y) * W + x
    else:
        lin = (b * H + y) * W + x
    lin = torch.where(ok, lin, torch.zeros_like(lin))
    n = B * H * W * (2 if by_polarity else 1)
    counts = torch.bincount(lin, weights=ok.to(torch.float32), minlength=n)[:n]
    return counts.to(torch.float32).reshape(shape)
