"""The ideal pixel's log-interpolation step on every pixel at once: what ``emulator.compile`` fuses.

:func:`dvsland.events.emulator.emulator_step`'s torch path first picks the candidate pixels (those
whose level moved by about a threshold or more: a host sync), gathers their values and runs some
forty elementwise passes over them. :func:`pixel_step_dense` is the same formulas over all pixels,
the candidate rule a mask: no gather, no sync, one pure function of tensors that ``torch.compile``
turns into a few fused kernels on a GPU (``emulator.compile``). Per pixel the operations are those of
the candidate path (``_pixel_events``), and the closed form of the emitted crossings
(:func:`emitted_dense`, with :func:`crossing_times` and :func:`refractory_binds`) is the one that path
runs too, so run eagerly or traced without code generation it gives the same bits; inductor's fused
code equals them within float rounding (tests/test_emulator_compile.py).
"""

from __future__ import annotations

from typing import Tuple, Union

import torch

Num = Union[float, torch.Tensor]


def pixel_step_dense(l1: torch.Tensor, lref: torch.Tensor, l0: torch.Tensor, tlast: torch.Tensor, th_on: Num,
                     th_off: Num, r: Num, t0: torch.Tensor, dt: float, spacing_may_bind: bool, same: bool,
                     tol: float) -> Tuple[torch.Tensor, ...]:
    """One step of B x H x W ideal pixels (log interpolation between the frames' levels).

    Args:
        l1, lref, l0: (B, H, W) float64 the new level, the reference level and the last frame's level.
        tlast: (B, H, W) float64 µs, each pixel's last event time (-inf = none).
        th_on, th_off: the thresholds, floats or (B, H, W) float64 maps; ``same``: both one float.
        r: the refractory period, µs: a float or (B, 1, 1) float64 per descent.
        t0: () float64 µs, the step's start; dt: its length, µs.
        spacing_may_bind: False when every crossing's spacing is known to be >= r.
        tol: the level tolerance (``LEVEL_TOL``) of the crossing counts.

    Returns:
        (lref_new, tlast_new, cnt, first, step_us, off, sizes): each of the first six (B, H, W): the new
        reference level and last event time (float64), the events emitted (float64 whole numbers, 0 where
        none), the first one's time and the spacing (µs after t0, float64; meaningful where cnt > 0) and
        the OFF flag (bool); sizes (3,) float64: the events, the pixels with one or more, and those with
        two or more (the compactions' sizes, summed in the same fused pass).
    """
    d = l1 - lref
    shrink = 1.0 - 2 * tol
    if same:
        cand = d.abs() >= th_on * shrink
        n = torch.floor((d / th_on).abs() + tol)
        th = torch.sign(d) * th_on
    else:
        on = th_on if isinstance(th_on, torch.Tensor) else torch.full_like(d, th_on)
        off = th_off if isinstance(th_off, torch.Tensor) else torch.full_like(d, th_off)
        cand = (d >= on * shrink) | (d <= off * -shrink)
        n = torch.floor(d / on + tol).clamp(min=0) + torch.floor(-d / off + tol).clamp(min=0)
        th = torch.where(d > 0, on, -off)
    cnt, first, step, t_last = emitted_dense(n, th, lref, l0, l1, dt, tlast - t0, r, spacing_may_bind)
    cnt = torch.where(cand, cnt, torch.zeros_like(cnt))
    lref_new = torch.where(cand, torch.addcmul(lref, n, th), lref)
    has = cnt > 0
    tlast_new = torch.where(has, t_last + t0, tlast)
    sizes = torch.stack([cnt.sum(), has.sum().to(cnt.dtype), (cnt > 1).sum().to(cnt.dtype)])
    return lref_new, tlast_new, cnt, first, step, torch.signbit(th), sizes


def crossing_times(th, lref, l0, l1, dt: float):
    """(base, spacing, first) µs after the step start, each shaped as the inputs (float64): crossing j of
    a pixel is at base + j spacing (log interpolation: equally spaced), the first at base + spacing; th
    the signed threshold, lref, l0, l1 the reference, last and new levels, dt the step, µs. Where the
    level did not move (l1 = l0) the values are inf or NaN: such a pixel has no crossing to time."""
    scale = dt / (l1 - l0)
    spacing = th * scale
    base = (lref - l0) * scale
    return base, spacing, base + spacing


def refractory_binds(first, spacing, tl, r: Num, spacing_may_bind: bool):
    """Where the refractory period ``r`` (µs; a float or broadcastable tensor) may drop crossings (bool):
    crossings closer than r (tested only where ``spacing_may_bind``), or the first within r of the
    last emitted event at ``tl`` (µs after the step start, -inf = never)."""
    near = first < tl + r
    return (spacing < r) | near if spacing_may_bind else near


def emitted_dense(n, th, lref, l0, l1, dt: float, tl, r: Num, spacing_may_bind: bool):
    """(cnt, first, step, tlast): the emitted crossings of every pixel in closed form (the emulator's
    ``_emitted_log``, whose arguments and returns these are), the refractory rule evaluated everywhere
    and kept where :func:`refractory_binds`: no compaction, no host sync (the GPU's path and the traced
    step's; the CPU compacts the binding pixels first, where that is faster)."""
    base, spacing, first = crossing_times(th, lref, l0, l1, dt)
    cnt, step = n, spacing
    if isinstance(r, torch.Tensor) or r > 0:
        bind = refractory_binds(first, spacing, tl, r, spacing_may_bind)
        j0 = torch.ceil((tl - base + r) / spacing).clamp(min=1.0)
        m = torch.ceil(r / spacing).clamp(min=1.0)
        c = torch.floor((n - j0) / m).add(1.0).clamp(min=0.0).nan_to_num(0.0, 0.0, 0.0)
        cnt = torch.where(bind, c, n)
        first = torch.where(bind, torch.addcmul(base, j0, spacing), first)
        step = torch.where(bind, m * spacing, spacing)
    return cnt, first, step, first.addcmul(cnt - 1, step)


__all__ = ["crossing_times", "emitted_dense", "pixel_step_dense", "refractory_binds"]
