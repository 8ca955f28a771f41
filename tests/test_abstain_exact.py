"""The motion-evidence test's batched internals against the first (reference) implementation.

``motion_evidence`` counts rows by binary search and sums the flicker's moments by segment
reduction over events sorted by (b, t), and runs the neighbour box on the flat images (or takes
the counts and sums from the compiled kernel, in the same order); the
reference below (the implementation these replaced: bincount, ``index_add_``, strided box sums)
must give the same bits on random and structured windows, empty rows and odd sensor sizes.
"""

from __future__ import annotations

import pytest
import torch

from dvsland.estimators import abstain as A
from dvsland.events import Events


def _reference(events, B, sensor_size, t_us, p):
    """The first implementation of :func:`motion_evidence` (bincount, index_add_, strided boxes)."""
    W, H = sensor_size
    n = torch.bincount(events.b, minlength=B)[:B]
    occ = torch.zeros(B * (H + 2) * (W + 2), dtype=torch.uint8)
    occ[(events.b * (H + 2) + events.y + 1) * (W + 2) + events.x + 1] = 1
    padded = occ.view(B, H + 2, W + 2)
    img, cell = padded[:, 1:-1, 1:-1], max(2, int(p.cell_px))
    Hc, Wc = H // cell, W // cell
    if Hc * Wc < 2:
        clus = torch.zeros(B)
    else:
        acc = torch.uint8 if cell * cell <= 255 else torch.int32
        c = img[:, :Hc * cell, :Wc * cell].reshape(B, Hc, cell, Wc, cell).sum(dim=4, dtype=acc).sum(dim=2, dtype=acc)
        c = c.reshape(B, -1).to(torch.float32)
        m = c.mean(dim=1)
        den = m * (1.0 - m / (cell * cell))
        clus = torch.where(den > 1e-6, c.var(dim=1) / den.clamp_min(1e-6), torch.zeros_like(m))
    r = padded[:, :, :-2] + padded[:, :, 1:-1] + padded[:, :, 2:]
    box = r[:, :-2] + r[:, 1:-1] + r[:, 2:]
    with_nb = ((box - img).clamp_(max=1) * img).view(B, -1).sum(dim=1, dtype=torch.int32).to(torch.float32)
    active = padded.view(B, -1).sum(dim=1, dtype=torch.int32).to(torch.float32)
    obs, q = with_nb / active.clamp_min(1.0), active / float(H * W)
    exp = 1.0 - (1.0 - q) ** 8
    se = A.NEIGHBOUR_SD_INFLATION * torch.sqrt(exp * (1.0 - exp) / active.clamp_min(1.0))
    nbx = torch.where((active > 0) & (se > 0), (obs - exp) / se.clamp_min(1e-9), torch.zeros_like(q))
    t = (events.t - int(t_us)).to(torch.float32)
    t = t / t.abs().max().clamp_min(1.0)
    pol = events.p.to(torch.float32)
    sums = torch.zeros(4, B).index_add_(1, events.b, torch.stack([t, pol, t * t, pol * t]))
    nn = n.to(torch.float32).clamp_min(1.0)
    mt, mp = sums[0] / nn, sums[1] / nn
    vt, vp = sums[2] / nn - mt ** 2, 1.0 - mp ** 2
    cov = sums[3] / nn - mt * mp
    rr = cov.abs() / torch.sqrt((vt * vp).clamp_min(1e-12))
    flick = torch.where((vt > 1e-6) & (vp > 1e-6), rr, torch.zeros_like(rr)).clamp(0.0, 1.0)
    motion = torch.maximum(A._ramp(clus, p.clustering_none, p.clustering_full),
                           A._ramp(nbx, p.neighbours_none, p.neighbours_full))
    motion = torch.maximum(motion, A._ramp(q, p.saturated_from, p.saturated_full))  # most pixels active
    motion = motion * A._ramp(flick, p.flicker_none, p.flicker_full)
    judged = A._ramp(n.to(torch.float32), float(p.min_events), float(p.full_events))
    factor = (1.0 - judged * (1.0 - motion)).clamp(0.0, 1.0)
    return A.MotionEvidence(factor, clus, nbx, flick, n)


def _window(g, B, W, H, N, structured):
    """N events of B rows (row B - 1 left empty when B > 1), sorted by (b, t); ``structured``:
    on a few lines (edges) with a polarity that flips in time, else uniform noise."""
    b = torch.randint(0, max(B - 1, 1), (N,), generator=g)
    t = torch.randint(0, 100_000, (N,), generator=g)
    if structured:
        y = (torch.randint(0, 4, (N,), generator=g) * (H // 4)).clamp(max=H - 1)
        x = torch.randint(0, W, (N,), generator=g)
        p = torch.where(t < 50_000, 1, -1).to(torch.int8)
    else:
        x, y = torch.randint(0, W, (N,), generator=g), torch.randint(0, H, (N,), generator=g)
        p = (torch.randint(0, 2, (N,), generator=g) * 2 - 1).to(torch.int8)
    return Events(b, x, y, t, p, sort=True)


# the compiled counts take a dense pass over the pixels from one event per 10 pixels, else go event by
# event: (4, 64, 64, 500) and (6, 50, 40, 700) are the sparse windows
@pytest.mark.parametrize("B,W,H,N", [(3, 40, 30, 900), (1, 9, 9, 60), (5, 128, 128, 30000), (4, 33, 17, 3000),
                                     (2, 7, 7, 10), (4, 64, 64, 500), (6, 50, 40, 700)])
@pytest.mark.parametrize("structured", [False, True])
@pytest.mark.parametrize("cell", [8, 3, 16])
@pytest.mark.parametrize("compiled", [False, True])
def test_motion_evidence_matches_reference_bit_for_bit(B, W, H, N, structured, cell, compiled):
    """On the torch path and with the compiled counts (dvsland.events.native, where a compiler is found)."""
    from dvsland.events import native

    if compiled and native.load() is None:
        pytest.skip("no C++ compiler here")
    g = torch.Generator().manual_seed(B * 1000 + N + cell + structured)
    ev = _window(g, B, W, H, N, structured)
    p = A.AbstainParams(cell_px=cell)
    with native.native_sort_mode(compiled):
        got = A.motion_evidence(ev, B, (W, H), 100_000, p)
    ref = _reference(ev, B, (W, H), 100_000, p)
    for name, a, r in zip(A.MotionEvidence._fields, got, ref):
        assert a.dtype == r.dtype and torch.equal(a, r), (name, a, r)


def test_flicker_row_sums_are_the_scatter_sums():
    """The segment reduction adds each row's events in their order: the scatter's float32 sums."""
    g = torch.Generator().manual_seed(3)
    b = torch.sort(torch.randint(0, 6, (5000,), generator=g)).values
    src = torch.randn(4, 5000, generator=g) * 1e3
    n = torch.bincount(b, minlength=7)
    ref = torch.zeros(4, 7).index_add_(1, b, src)
    assert torch.equal(A._row_sums(src, b, n), ref)
