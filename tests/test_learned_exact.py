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
