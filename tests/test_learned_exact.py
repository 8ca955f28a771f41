"""The learned update's cheaper internals give the bits of the first implementation.

The ring net (:class:`RingCNN`) scales, shifts and rectifies the first layer in place and runs the
rest as convolutions with in-place ReLUs; the voxel grid builds its flat index with fused
multiply-adds. Each is compared here with the reference computation it replaced (out-of-place
``addcdiv``, the ``nn.Sequential`` of the features, the index as products and sums), bit for bit.
"""

from __future__ import annotations

import pytest
import torch
from torch.nn import functional as F

from dvsland.estimators.learned import InputSpec, VoxelCNN, coord_channels, voxel_grid
from dvsland.estimators.learned.fast import RingCNN


def _reference_ring(net: RingCNN, ring, abs_sums, newest: int, log_count):
    """The first RingCNN.forward: addcdiv, then the features' Sequential (ReLU, conv, ...)."""
    B, nb, h, w = ring.shape
    wq = net.w_by_newest[newest]
    s = (abs_sums.sum(1) / float(nb * h * w)).clamp_min(1e-3)
    if net.dtype != torch.float32:
        ring = ring.to(net.dtype).contiguous(memory_format=torch.channels_last)
    y = F.conv2d(ring, wq, None, net.stride, net.padding)
    y = torch.addcdiv(net.const, y, s.view(B, 1, 1, 1).to(net.dtype))
    f = net.rest(y).float()
    f = torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3)), log_count[:, None]], dim=1)
    mu, log_var = net.head(f).unbind(1)
    return mu, log_var.clamp(-12.0, 6.0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("K", [1, 4])
def test_ring_net_matches_the_reference_bit_for_bit(dtype, K):
    torch.manual_seed(K)
    net = VoxelCNN(n_bins=4, width=8).eval()
    spec = InputSpec((64, 48), 4, 2, n_windows=K)
    rn = RingCNN(net, coord_channels(spec, (31.5, 23.5)), K, dtype=dtype)
    ring = torch.randint(-3, 4, (5, 4, *spec.grid_hw)).to(torch.float32)
    abs_sums = ring.abs().view(5, K, -1).sum(2)
    log_count = torch.log1p(torch.full((5,), 700.0))
    with torch.no_grad():
        for q in range(K):
            got = rn(ring, abs_sums, torch.full((5,), q), log_count)
            ref = _reference_ring(rn, ring, abs_sums, q, log_count)
            assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1]), (q, got, ref)


@pytest.mark.parametrize("K", [1, 4])
def test_ring_net_channels_last_matches_the_default_layout(K):
    """The float32 ring channels-last (what a GPU runs) gives the default layout's numbers."""
    torch.manual_seed(K)
    net = VoxelCNN(n_bins=4, width=8).eval()
    spec = InputSpec((64, 48), 4, 2, n_windows=K)
    coords = coord_channels(spec, (31.5, 23.5))
    plain, cl = RingCNN(net, coords, K), RingCNN(net, coords, K, channels_last=True)
    assert cl.channels_last and not plain.channels_last
    ring = torch.randint(-3, 4, (5, 4, *spec.grid_hw)).to(torch.float32)
    abs_sums = ring.abs().view(5, K, -1).sum(2)
    log_count = torch.log1p(torch.full((5,), 700.0))
    with torch.no_grad():
        for q in range(K):
            got, ref = cl(ring, abs_sums, torch.full((5,), q), log_count), plain(ring, abs_sums, q, log_count)
            assert all(torch.allclose(a, b, rtol=1e-5, atol=1e-5) for a, b in zip(got, ref))


def test_ring_net_refuses_an_unknown_feature_layout():
    net = VoxelCNN(n_bins=4, width=8).eval()
    net.features[2] = torch.nn.Identity()
    with pytest.raises(ValueError, match="RingCNN"):
        RingCNN(net, torch.zeros(1, 2, 8, 8), 1)


@pytest.mark.parametrize("pool_px", [2, 3])
@pytest.mark.parametrize("K", [1, 4])
def test_voxel_grid_index_matches_the_products(pool_px, K):
    """The grid of many events (cells hit many times) equals the one built from the index
    b (nb h w) + (y // P) w + x // P written as products and sums."""
    g = torch.Generator().manual_seed(pool_px + K)
    spec = InputSpec((40, 30), 4, pool_px, n_windows=K)
    nb, (h, w) = spec.bins_per_window, spec.grid_hw
    N, B = 5000, 3
    b = torch.sort(torch.randint(0, B, (N,), generator=g)).values
    x, y = torch.randint(0, 40, (N,), generator=g), torch.randint(0, 30, (N,), generator=g)
    frac = torch.rand(N, generator=g)
    p = (torch.randint(0, 2, (N,), generator=g) * 2 - 1).to(torch.int8)
    got = voxel_grid(b, x, y, frac, p, B, spec, nb)
    base = b * (nb * h * w) + (y // pool_px) * w + x // pool_px
    pol = p.to(torch.float32)
    if K > 1:
        if nb > 1:
            base = base + (frac * nb).long().clamp(0, nb - 1) * (h * w)
        ref = torch.bincount(base, weights=pol, minlength=B * nb * h * w).to(torch.float32)
    else:
        ref = torch.zeros(B * nb * h * w)
        tb = frac.clamp(0.0, 1.0) * (nb - 1)
        lo = tb.floor().long().clamp(max=nb - 1)
        hi = (lo + 1).clamp(max=nb - 1)
        wt = tb - lo.to(torch.float32)
        ref.index_put_((base + lo * (h * w),), pol * (1.0 - wt), accumulate=True)
        ref.index_put_((base + hi * (h * w),), pol * wt, accumulate=True)
    assert torch.equal(got, ref.view(B, nb, h, w))


def _conv_batches(monkeypatch) -> list:
    """The batch sizes every convolution runs on from now on in this test."""
    sizes, real = [], F.conv2d
    monkeypatch.setattr(F, "conv2d", lambda x, *a, **k: sizes.append(x.shape[0]) or real(x, *a, **k))
    return sizes


def _ring_case(B: int, K: int = 4, seed: int = 0):
    torch.manual_seed(seed)
    net = VoxelCNN(n_bins=4, width=8).eval()
    spec = InputSpec((64, 48), 4, 2, n_windows=K)
    rn = RingCNN(net, coord_channels(spec, (31.5, 23.5)), K)
    ring = torch.randint(-3, 4, (B, 4, *spec.grid_hw)).to(torch.float32)
    return rn, (ring, ring.abs().view(B, K, -1).sum(2), torch.full((B,), 2), torch.log1p(torch.full((B,), 700.0)))


@pytest.mark.parametrize("needed", [[], [3], [0, 5, 17], list(range(0, 30, 2)), list(range(29))])
def test_ring_net_rows_give_the_whole_batchs_bits(needed, monkeypatch):
    """forward_rows: the whole batch's mu and log_var at the needed rows (0 at rows not computed),
    before and after its one check of the rows' bits; a batch mostly needed runs whole."""
    from dvsland.estimators.learned import rows

    B = 30
    rn, args = _ring_case(B)
    need = torch.zeros(B, dtype=torch.bool)
    need[needed] = True
    with torch.no_grad():
        whole = rn(*args)
        for _ in range(2):  # the first call checks the rows against the whole batch, the second trusts it
            got = rn.forward_rows(*args, need)
            for g, w in zip(got, whole):
                assert torch.equal(g[need], w[need])
    k = max(len(needed), rows.MIN_ROWS)
    if not needed:  # nothing to run
        sizes = _conv_batches(monkeypatch)
        with torch.no_grad():
            assert all(torch.equal(g, torch.zeros(B)) for g in rn.forward_rows(*args, need))
        assert rn._rows_exact == {} and sizes == []
    elif k > rows.ROWS_SHARE * B:
        assert rn._rows_exact == {}
    else:
        assert set(rn._rows_exact) == {(B, k)}
        if not rn._rows_exact[(B, k)]:
            pytest.skip(f"this CPU's convolution rounds {k} rows apart from {B}: the whole batch runs")
        sizes = _conv_batches(monkeypatch)
        with torch.no_grad():
            rn.forward_rows(*args, need)
        assert sizes and set(sizes) == {k}  # only k rows went through


def test_ring_net_rows_fall_back_to_the_whole_batch_where_the_bits_differ(monkeypatch):
    """A (batch, rows) size whose check failed runs the whole batch: the whole batch's bits."""
    B = 30
    rn, args = _ring_case(B, seed=1)
    need = torch.zeros(B, dtype=torch.bool)
    need[[1, 2]] = True
    rn._rows_exact[(B, 8)] = False
    sizes = _conv_batches(monkeypatch)
    with torch.no_grad():
        got, whole = rn.forward_rows(*args, need), rn(*args)
    assert all(torch.equal(g, w) for g, w in zip(got, whole))
    assert sizes and set(sizes) == {B}


@pytest.mark.parametrize("checkpoint", ["", "spiking"])
def test_learned_step_on_a_few_flying_rows_is_the_whole_batchs(monkeypatch, checkpoint):
    """The shipped CNN's and spiking model's step on a batch where few rows have events (finished
    descents: none) runs the network on those rows only and gives the whole batch's estimates,
    confidences and state (the spiking model's activity too, at the rows with an estimate)."""
    from dvsland.estimators import get_estimator
    from dvsland.estimators.learned import rows
    from dvsland.events import Events

    B, g = 20, torch.Generator().manual_seed(3)

    def window(k: int, rows=(2, 7, 11)):
        n = 400
        b = torch.tensor(rows).repeat_interleave(n)
        t = torch.randint((k - 1) * 100_000, k * 100_000, (b.numel(),), generator=g)
        order = torch.argsort(b * 10**9 + t)
        xy = torch.randint(0, 128, (2, b.numel()), generator=g)
        p = torch.randint(0, 2, (b.numel(),), generator=g) * 2 - 1
        return Events(b[order], xy[0][order], xy[1][order], t[order], p[order])

    def fly(share: float):
        monkeypatch.setattr(rows, "ROWS_SHARE", share)
        est = get_estimator("learned", B, (128, 128), min_events=20, checkpoint=checkpoint)
        st, outs = est.init_state(), []
        for k, ev in enumerate(windows, start=1):
            st, out = est.step_state(st, ev, k * 100_000)
            outs.append(out)
        return est, st, outs

    windows = [window(k) for k in range(1, 7)]
    est, st, outs = fly(rows.ROWS_SHARE)
    exact = est.consts.ring_net._rows_exact if est.consts.ring_net is not None else est.consts.rows_exact
    assert exact  # the rows' path was taken (and checked once)
    _, st_whole, outs_whole = fly(-1.0)  # the whole batch every step
    for a, w in zip(outs, outs_whole):
        assert torch.equal(a.d_hat.isnan(), w.d_hat.isnan()) and torch.equal(a.d_hat.nan_to_num(), w.d_hat.nan_to_num())
        assert torch.equal(a.confidence, w.confidence)
        for k in ("spikes", "synops"):
            assert (k in a.diagnostics) == (k in w.diagnostics) == (checkpoint == "spiking")
            if k in a.diagnostics:
                has, x, y = a.diagnostics["sigma_rel"].isfinite(), a.diagnostics[k], w.diagnostics[k]
                assert torch.equal(x[has], y[has])
                assert bool(((x == 0) | (x == y))[~has].all())  # not run: none (a padding row: its own)
    assert int(st.d.isfinite().sum()) == 3  # the network's estimates (random events: the motion gate abstains)
    for a, w in zip(st, st_whole):
        assert torch.equal(a.nan_to_num(), w.nan_to_num())
