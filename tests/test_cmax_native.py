"""cmax's compiled splat kernel (dvsland.estimators.native_cmax) against the torch path, the reference.

The kernel's image sums are integers (corner weights in 1 / WEIGHT_UNIT of an event), so it must give
the torch path's scores and estimates exactly. The comparisons run where the kernel is built
(built here on first use, a second or two, where a C++ compiler is found; skipped without one).
"""

from __future__ import annotations

import math

import pytest
import torch

from dvsland.estimators import get_estimator, native_cmax
from dvsland.estimators.cmax import hot_pixel_weights, store_keep
from dvsland.estimators.contrast import WEIGHT_UNIT, split_contrast
from dvsland.events import Events


def _events(B=5, n=3000, seed=0, W=128, H=128):
    """Random events of B elements: a few bright edges zooming out about the centre, plus noise."""
    g = torch.Generator().manual_seed(seed)
    b = torch.randint(0, B, (n,), generator=g)
    r0 = 5 + 50 * torch.rand(n, generator=g)
    ang = (torch.randint(0, 24, (n,), generator=g).to(torch.float64) / 24 * 2 * math.pi)
    t_us = torch.randint(0, 1_000_000, (n,), generator=g)
    d = -0.05 - 0.02 * b.to(torch.float64)
    r = r0 * torch.exp(-d * t_us * 1e-6)
    x = (63.5 + r * torch.cos(ang)).round().clamp(0, W - 1).to(torch.int64)
    y = (63.5 + r * torch.sin(ang)).round().clamp(0, H - 1).to(torch.int64)
    p = torch.where(torch.rand(n, generator=g) < 0.5, 1, -1).to(torch.int8)
    return Events(b, x, y, t_us, p, sort=True)


def _score_args(seed=0, E=20000, B=7, G=3):
    g = torch.Generator().manual_seed(seed)
    xc = 1 + 128 * torch.rand(E, generator=g) - 0.5
    yc = 1 + 128 * torch.rand(E, generator=g) - 0.5
    b = torch.randint(0, B, (E,), generator=g)
    half = torch.randint(0, 2, (E,), generator=g)
    dt = (torch.rand(E, generator=g) - 0.5).to(torch.float32)
    cand = -0.3 * torch.rand(B, G, generator=g, dtype=torch.float64) + 0.05
    hw = 0.5 * torch.ones(B, dtype=torch.float64)
    wt = (0.1 + 3 * torch.rand(E, generator=g)).to(torch.float32)
    return (xc, yc, b, half, dt, cand, (64.5, 64.5), (130, 130), (0.5, 128.5, 0.5, 128.5), hw, wt)


def test_weight_unit_is_a_power_of_two():
    assert WEIGHT_UNIT == 2.0 ** round(math.log2(WEIGHT_UNIT))


def test_mode_reads_the_environment(monkeypatch):
    native_cmax.use_native_cmax(None)
    monkeypatch.setenv("DVSLAND_NATIVE_CMAX", "off")
    assert native_cmax.mode() == "off" and not native_cmax.enabled()
    monkeypatch.setenv("DVSLAND_NATIVE_CMAX", "maybe")
    with pytest.raises(ValueError, match="DVSLAND_NATIVE_CMAX"):
        native_cmax.mode()
    monkeypatch.delenv("DVSLAND_NATIVE_CMAX")
    assert native_cmax.mode() == "auto"


def test_torch_path_scores_match_the_float_splat():
    """The integer weights move the score by < 1e-5 relative against a float64 bilinear splat."""
    xc, yc, b, half, dt, cand, cen, hw_canvas, box, hw, wt = _score_args(E=5000, B=2, G=3)
    got = split_contrast(xc, yc, b, half, dt, cand, cen, hw_canvas, box, hw, wt, native=False)
    # float64 reference of the same score
    Hc, Wc = hw_canvas
    ref = torch.zeros_like(got)
    for bi in range(2):
        for gi in range(3):
            m = b == bi
            d = cand[bi, gi]
            s = torch.exp(d.float() * dt[m])
            xw, yw = (xc[m] - cen[0]) * s + cen[0], (yc[m] - cen[1]) * s + cen[1]
            ginv = math.exp(-abs(float(d)) * 0.5)
            ins = ((xw >= cen[0] + (box[0] - cen[0]) * ginv) & (xw <= cen[0] + (box[1] - cen[0]) * ginv)
                   & (yw >= cen[1] + (box[2] - cen[1]) * ginv) & (yw <= cen[1] + (box[3] - cen[1]) * ginv))
            ims = torch.zeros(2, Hc * Wc, dtype=torch.float64)
            x0, y0 = xw.floor(), yw.floor()
            fx, fy = (xw - x0).double(), (yw - y0).double()
            w = wt[m].double() * ins.double()
            for dx, dy, ww in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
                idx = ((y0.long() + dy) * Wc + x0.long() + dx).clamp(0, Hc * Wc - 1)  # outside: weight 0
                ims.index_put_((half[m], idx), w * ww, accumulate=True)
            area = (box[1] - box[0]) * (box[3] - box[2]) * ginv ** 2
            n = ims.sum(1)
            na = n.sum()
            i0, i1 = ims
            ref[bi, gi, 0] = ((i0 + i1) ** 2).sum() / na - na / area
            ref[bi, gi, 1] = (i0 ** 2).sum() / n[0] - n[0] / area
            ref[bi, gi, 2] = (i1 ** 2).sum() / n[1] - n[1] / area
    assert torch.allclose(got, ref, rtol=1e-5, atol=0)


def _need_kernel():
    if native_cmax.load(force=True) is None:
        pytest.skip("no C++ compiler here")


@pytest.mark.parametrize("seed,B,G", [(0, 7, 3), (1, 3, 21), (2, 1, 9)])
def test_kernel_scores_equal_torch_path(seed, B, G):
    _need_kernel()
    args = _score_args(seed=seed, B=B, G=G)
    ref = split_contrast(*args, native=False)
    got = split_contrast(*args, native=True)
    assert torch.equal(got, ref)
    # without weights, and with an element that has no events
    a = list(args)
    a[10] = None
    a[2] = torch.where(a[2] == 0, torch.ones_like(a[2]) * min(1, B - 1), a[2])
    assert torch.equal(split_contrast(*a, native=True), split_contrast(*a, native=False))


def test_kernel_heavy_weights_take_the_wide_canvas_and_too_heavy_ones_are_refused():
    """Weights of 10^4 events: an element's total passes 2^31 / WEIGHT_UNIT, so the kernel sums in an
    int64 canvas, still equal to the torch path; a weight of 2^18 events (its int32 corner weights
    would overflow) or a NaN one is refused with the reason, never summed wrongly."""
    _need_kernel()
    args = list(_score_args(seed=3, E=3000, B=2, G=3))
    args[10] = args[10] * 1e4
    assert torch.equal(split_contrast(*args, native=True), split_contrast(*args, native=False))
    for bad in (2.0 ** 18, float("nan")):
        args[10] = torch.ones_like(args[10])
        args[10][7] = bad
        with pytest.raises(RuntimeError, match="event weight not finite or of 2\\^18"):
            split_contrast(*args, native=True)


def test_kernel_estimates_equal_torch_path():
    """cmax at its defaults over a few updates: the same estimates, standard errors and windows."""
    _need_kernel()
    out = []
    for native in (False, True):
        native_cmax.use_native_cmax(native)
        try:
            est = get_estimator("cmax", batch_size=5, sensor_size=(128, 128), window_ms=400.0)
            ds = []
            for k in range(1, 9):
                ev = _events(seed=k)
                ev = Events(ev.b, ev.x, ev.y, ev.t + (k - 1) * 100_000, ev.p, sort=True)
                ds.append(est.update(ev, k * 100_000 + 1_000_000))
            out.append((torch.stack(ds), est.diagnostics()))
        finally:
            native_cmax.use_native_cmax(None)
    (d0, g0), (d1, g1) = out
    assert torch.equal(d0.isnan(), d1.isnan()) and torch.equal(d0.nan_to_num(), d1.nan_to_num())
    for k in ("window_s", "d_std", "contrast"):
        assert torch.equal(g0[k].nan_to_num(), g1[k].nan_to_num()), k


def test_kernel_builds_and_equals_torch_path():
    """Builds the kernel when it is not cached (a second or two of compiler CPU), then compares."""
    try:
        native_cmax.build()
    except Exception as exc:  # no compiler here: the torch path is what runs
        pytest.skip(f"cannot build the kernel: {exc}")
    args = _score_args(seed=5, B=4, G=3)
    native_cmax.use_native_cmax(True)
    try:
        assert torch.equal(split_contrast(*args, native=True), split_contrast(*args, native=False))
    finally:
        native_cmax.use_native_cmax(None)


@pytest.mark.parametrize("hot,runs", [(True, False), (False, False), (True, True), (False, True)])
def test_kernel_hot_pixel_weights_and_counts_equal_torch_path(hot, runs):
    """Elements with a hot pixel (two rounds) and without (the first round flags nothing), events
    in random element order and in runs of one element (as the store holds them: each step sorted)."""
    _need_kernel()
    from dvsland.estimators.contrast import pixel_counts

    g = torch.Generator().manual_seed(3)
    B, n_px, E = 6, 32 * 32, 20000
    b = torch.randint(0, B - 1, (E,), generator=g)  # the last element has no events
    if runs:  # four stored steps, each sorted by element
        b = torch.cat([c.sort().values for c in b.chunk(4)])
    pix = torch.randint(0, n_px, (E,), generator=g)
    if hot:
        pix = torch.where(torch.rand(E, generator=g) < 0.1, torch.full((E,), 77), pix)
    assert torch.equal(pixel_counts(b, pix, B, n_px, native=True), pixel_counts(b, pix, B, n_px, native=False))
    est = get_estimator("cmax", B, (32, 32))
    out = []
    for native in (False, True):
        native_cmax.use_native_cmax(native)
        try:
            out.append(hot_pixel_weights(est.params, est.setup, pix, b))
        finally:
            native_cmax.use_native_cmax(None)
    assert torch.equal(out[0], out[1]) and bool((out[0] < 1).any()) == hot


@pytest.mark.parametrize("max_events,seed", [(4000, 0), (300, 2 ** 62 + 12345), (0, 7)])
def test_kernel_store_thinning_equals_torch_path(max_events, seed):
    """The events kept at store time (on the sensor, in the batch, hash-thinned per element)."""
    _need_kernel()
    g = torch.Generator().manual_seed(11)
    E = 50000
    b = torch.randint(-1, 5, (E,), generator=g)  # -1 and 4 (B = 4) are outside the batch
    x = torch.randint(-2, 34, (E,), generator=g)
    y = torch.randint(-2, 34, (E,), generator=g)
    t = torch.randint(0, 10 ** 9, (E,), generator=g)
    est = get_estimator("cmax", 4, (32, 32), max_events=max_events, seed=seed)
    out = []
    for native in (False, True):
        native_cmax.use_native_cmax(native)
        try:
            out.append(store_keep(est.params, est.setup, est.state, b, x, y, t))
        finally:
            native_cmax.use_native_cmax(None)
    assert torch.equal(out[0], out[1]) and 0 < out[0].numel() < E


@pytest.mark.parametrize("max_events,min_events", [(4000, 50), (150, 1), (0, 2000), (0, 10000)])
def test_kernel_window_gather_equals_torch_path(max_events, min_events):
    """The stored events of each element's window (time range, hash thinning to max_events), the
    elements that estimate (min_events, a filled first window) and the gather of their events as
    the score takes them: the kernel's counts and events against _window_mask + _gather."""
    _need_kernel()
    from dvsland.estimators.cmax import _window_events

    g = torch.Generator().manual_seed(5)
    N, B = 30000, 5
    est = get_estimator("cmax", B, (32, 32), max_events=max_events, min_events=min_events)
    st = est.state._replace(
        ev_b_packed=torch.randint(0, B - 1, (N,), generator=g),  # element 4 stores nothing
        ev_x_packed=32 * torch.rand(N, generator=g), ev_y_packed=32 * torch.rand(N, generator=g),
        ev_t_packed=torch.randint(0, 3_000_000, (N,), generator=g),
        ev_key_packed=torch.randint(0, 2 ** 40, (N,), generator=g),
        window_s=torch.tensor([0.5, 1.0, 2.5, 0.01, 1.0], dtype=torch.float64))
    filled = torch.tensor([True, False, True, True, True])
    out = []
    for native in (False, True):
        native_cmax.use_native_cmax(native)
        try:
            out.append(_window_events(est.params, est.setup, st, 2_600_000, filled))
        finally:
            native_cmax.use_native_cmax(None)
    (n0, ok0, ev0), (n1, ok1, ev1) = out
    assert torch.equal(n0, n1) and torch.equal(ok0, ok1) and n0[4] == 0
    assert bool(ok0.any()) == (ev0 is not None) == (ev1 is not None)
    if ev0 is not None:
        assert all(a.dtype == c.dtype and torch.equal(a, c) for a, c in zip(ev0, ev1))
        assert set(ev0[0].unique().tolist()) <= set(ok0.nonzero().squeeze(1).tolist())
        if max_events:  # thinned: fewer kept than in the windows
            assert ev0[0].numel() < int(n0[ok0].sum())


def test_kernel_radial_and_event_weights_equal_torch_path():
    """Radial weights alone and radial x hot-pixel weights (an element without events, a hot pixel)."""
    _need_kernel()
    from dvsland.estimators.cmax import _event_weights, radial_weights

    g = torch.Generator().manual_seed(8)
    B, E = 5, 20000
    b = torch.randint(0, B - 1, (E,), generator=g)
    pix = torch.where(torch.rand(E, generator=g) < 0.05, torch.full((E,), 500), torch.randint(0, 64 * 64, (E,),
                                                                                               generator=g))
    est = get_estimator("cmax", B, (64, 64))
    out = []
    for native in (False, True):
        native_cmax.use_native_cmax(native)
        try:
            p, setup = est.params, est.setup
            out.append((radial_weights(p, setup, pix, b), _event_weights(p, setup, pix, b)))
        finally:
            native_cmax.use_native_cmax(None)
    (r0, w0), (r1, w1) = out
    assert torch.equal(r0, r1) and torch.equal(w0, w1) and not torch.equal(r0, w0)
    assert float(r0.min()) >= 0.1 and float(r0.max()) <= 10.0


def test_kernel_noise_floor_sums_equal_torch_path():
    """The noise floor's per-element sums of w and w^2 (two index_add_ in event order) from one compiled
    pass: the same float64 bits, an element without events at 4/9."""
    _need_kernel()
    from dvsland.estimators.cmax import NOISE_FLOOR_SCORE, _noise_floor

    g = torch.Generator().manual_seed(5)
    B, E = 7, 50000
    b = torch.randint(0, B - 1, (E,), generator=g)  # the last element has no events
    wt = torch.rand(E, generator=g).mul_(3.0)
    out = []
    for native in (False, True):
        native_cmax.use_native_cmax(native)
        try:
            out.append(_noise_floor(b, wt, B, b.device))
        finally:
            native_cmax.use_native_cmax(None)
    assert out[0].dtype == out[1].dtype == torch.float64
    assert torch.equal(out[0], out[1]) and float(out[1][-1]) == NOISE_FLOOR_SCORE
    with pytest.raises(RuntimeError, match="out of range"):
        native_cmax.load(force=True).weight_sums(torch.tensor([0, B]), wt[:2].contiguous(), B)
