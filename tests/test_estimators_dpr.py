"""The paper's estimator: DPR, mean-shift, Eq. 8 and the 'dpr' estimator (kornia-style tests)."""

from __future__ import annotations

import math

import pytest
import torch

from dvsland.estimators import get_estimator
from dvsland.estimators.density_peaks import density_peaks
from dvsland.estimators.divergence import pairwise_divergence
from dvsland.estimators.dpr import DPREstimator, capped_window
from dvsland.estimators.meanshift import meanshift_flat
from dvsland.evaluate.synthetic import blob_layout, zoom_blob_events
from dvsland.events import Events

W = H = 64


def _plant(image, x, y, amp, sigma=1.0):
    yy, xx = torch.meshgrid(torch.arange(image.shape[-2], dtype=torch.float32),
                            torch.arange(image.shape[-1], dtype=torch.float32), indexing="ij")
    image += amp * torch.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma ** 2))


# ---------------------------------------------------------------- DPR
def test_density_peaks_rank_order(device):
    img = torch.zeros(2, H, W)
    blobs = [(10, 12, 50.0), (40, 20, 30.0), (25, 50, 80.0), (52, 52, 10.0)]
    for x, y, a in blobs:
        _plant(img[0], x, y, a)
    _plant(img[1], 30, 30, 5.0)
    peaks, dens, valid = density_peaks(img.to(device), n_max=5, sigma_px=2.0)
    assert peaks.shape == (2, 5, 2) and dens.shape == (2, 5) and valid.shape == (2, 5)
    want = sorted(blobs, key=lambda b: -b[2])
    got = peaks[0, :4].cpu()
    assert torch.equal(got, torch.tensor([[x, y] for x, y, _ in want], dtype=torch.float32))
    assert valid[0, :4].all() and not valid[0, 4] and torch.isnan(peaks[0, 4]).all()
    assert (dens[0, :3] >= dens[0, 1:4]).all()
    assert valid[1].sum() == 1 and torch.equal(peaks[1, 0].cpu(), torch.tensor([30.0, 30.0]))


def test_density_peaks_empty_and_errors():
    peaks, dens, valid = density_peaks(torch.zeros(3, 8, 8), 4)
    assert not valid.any() and torch.isnan(peaks).all() and (dens == 0).all()
    with pytest.raises(ValueError, match="n_max"):
        density_peaks(torch.zeros(1, 8, 8), 0)
    with pytest.raises(ValueError, match="sigma_px"):
        density_peaks(torch.zeros(1, 8, 8), 2, sigma_px=0.0)
    with pytest.raises(ValueError, match="image"):
        density_peaks(torch.zeros(8, 8), 2)


# ---------------------------------------------------------------- mean-shift
def test_meanshift_converges_to_known_centroid(device):
    img = torch.zeros(1, H, W)
    # a symmetric cluster around (20.25, 30.5): centroid known exactly
    pts = [(20, 30), (21, 30), (20, 31), (21, 31), (19, 30), (22, 31)]
    for x, y in pts:
        img[0, y, x] += 10.0
    cx = sum(p[0] for p in pts) / len(pts)
    cy = sum(p[1] for p in pts) / len(pts)
    seeds = torch.tensor([[[cx + 2.5, cy - 2.0]]])
    c, counts, n_iter = meanshift_flat(img.to(device), seeds.to(device), torch.tensor([[True]], device=device),
                                       radius_px=4.0, iters=50, tol_px=1e-4)
    assert torch.allclose(c[0, 0].cpu(), torch.tensor([cx, cy]), atol=1e-5)
    assert counts[0, 0].item() == pytest.approx(60.0)
    assert int(n_iter) < 50


def test_meanshift_invalid_and_empty_seeds():
    img = torch.zeros(1, 16, 16)
    img[0, 8, 8] = 5
    seeds = torch.tensor([[[8.0, 8.0], [2.0, 2.0], [float("nan"), 1.0]]])
    valid = torch.tensor([[True, True, False]])
    c, counts, _ = meanshift_flat(img, seeds, valid, 3.0)
    assert torch.equal(c[0, 0], torch.tensor([8.0, 8.0]))
    assert torch.isnan(c[0, 1:]).all() and (counts[0, 1:] == 0).all()


def _estimator(B=1, **kw):
    params = dict(n_max=15, n_min=15, radius_px=4.0, c_min=3, r_min_px=3.0, memory_ms=500.0)
    params.update(kw)
    return DPREstimator(B, (W, H), dt_s=0.1, **params)


def _events_from_points(points, b=0, t_us=100_000):
    x = torch.tensor([p[0] for p in points])
    y = torch.tensor([p[1] for p in points])
    n = len(points)
    return Events(torch.full((n,), b), x, y, torch.full((n,), t_us), torch.ones(n, dtype=torch.int8))


def _cluster(x, y, n):
    return [(x + (i % 3) - 1, y + (i // 3) % 3 - 1) for i in range(n)]


def test_dpr_drops_thin_and_edge_clusters():
    est = _estimator(n_min=15, r_min_px=3.0, c_min=2)
    pts = _cluster(20, 20, 30) + _cluster(40, 40, 30) + _cluster(20, 45, 8) + _cluster(1, 30, 30)
    est.update(_events_from_points(pts), 100_000)
    dg = est.diagnostics()
    c = dg["centroids"][0]
    kept = c[~torch.isnan(c[:, 0])]
    assert dg["n_tracked"][0].item() == 2 and dg["reinit"][0]
    near = lambda x, y: ((kept - torch.tensor([x, y], dtype=torch.float32)).norm(dim=1) < 1.0).any()  # noqa: E731
    assert near(20, 20) and near(40, 40)
    assert not near(20, 45)  # thin cluster: 8 < n_min events
    assert not near(1, 30)  # edge cluster: closer than r_min to the edge
    # the same clusters are kept once the rules allow them (so the drops above are the rules' doing)
    est2 = _estimator(n_min=5, r_min_px=0.5, c_min=2)
    est2.update(_events_from_points(pts), 100_000)
    c2 = est2.diagnostics()["centroids"][0]
    kept2 = c2[~torch.isnan(c2[:, 0])]
    near2 = lambda x, y: ((kept2 - torch.tensor([x, y], dtype=torch.float32)).norm(dim=1) < 1.0).any()  # noqa: E731
    assert near2(20, 45) and near2(1, 30)
    assert dg["centroids"].shape == (1, 15, 2) and dg["centroids"].dtype == torch.float32


# ---------------------------------------------------------------- Eq. 8
@pytest.mark.parametrize("scale", [1.01, 1.2, 0.95])
def test_eq8_exact_for_pure_zoom(scale):
    g = torch.Generator().manual_seed(1)
    prev = torch.rand(3, 10, 2, generator=g, dtype=torch.float64) * 100
    centre = torch.tensor([50.0, 40.0], dtype=torch.float64)
    cur = centre + (prev - centre) * scale
    valid = torch.ones(3, 10, dtype=torch.bool)
    valid[1, 5:] = False
    d, n = pairwise_divergence(prev, cur, valid, dt_s=0.1)
    assert torch.allclose(d.double(), torch.full((3,), (1 - scale) / 0.1, dtype=torch.float64), rtol=1e-5)
    assert n.tolist() == [45, 10, 45]
    assert (d < 0).all() == (scale > 1)


def test_eq8_no_pairs_is_nan():
    prev = torch.rand(2, 4, 2)
    valid = torch.tensor([[True, False, False, False], [False] * 4])
    d, n = pairwise_divergence(prev, prev, valid, 0.1)
    assert torch.isnan(d).all() and (n == 0).all()
    with pytest.raises(ValueError, match="dt_s"):
        pairwise_divergence(prev, prev, valid, 0.0)


# ---------------------------------------------------------------- the estimator
def _run_zoom(est, D, steps, seed=0, start=0, active=None, n_blobs=30):
    B = est.batch_size
    offsets = blob_layout(B, n_blobs, (W, H), extent=0.75, seed=seed)
    out = []
    for k in range(start, start + steps):
        ev = zoom_blob_events(offsets, D, k * 100_000, (k + 1) * 100_000, (W, H), events_per_blob=12,
                              sigma_px=0.6, seed=1000 * seed + k, active=active, device=est.device)
        out.append(est.update(ev, (k + 1) * 100_000))
    return torch.stack(out)


def test_dpr_tracks_known_zoom(device):
    D = torch.tensor([-0.3, -0.15, 0.0])
    est = get_estimator("dpr", 3, (W, H), device, dt_s=0.1, n_min=10, n_max=15, radius_px=3.0)
    d = _run_zoom(est, D.to(device), 15, n_blobs=12)
    late = d[8:].cpu()
    assert not torch.isnan(late).any() and torch.isfinite(late).all()
    med = late.median(0).values
    assert torch.allclose(med, D, atol=0.05), med
    assert med[0] < med[1] < 0.02  # sign: spreading features -> D < 0


def test_dpr_empty_single_and_lost_give_nan_then_recover():
    est = _estimator(B=2, n_min=10, radius_px=3.0)
    empty = Events.empty()
    for k in range(3):
        d = est.update(empty, (k + 1) * 100_000)
        assert d.shape == (2,) and d.dtype == torch.float32 and torch.isnan(d).all()
    d = est.update(None, 400_000)
    assert torch.isnan(d).all()
    d = est.update(_events_from_points([(30, 30)]), 500_000)  # a single event
    assert torch.isnan(d).all()
    D = torch.tensor([-0.2, -0.2])
    d = _run_zoom(est, D, 10, start=5, n_blobs=12)
    assert torch.isfinite(d[-3:]).all()
    # all centroids lost: the events stop for longer than the memory
    for k in range(15, 22):
        d = est.update(Events.empty(), (k + 1) * 100_000)
        assert not torch.isinf(d).any()
    assert torch.isnan(d).all() and (est.diagnostics()["n_tracked"] == 0).all()
    d = _run_zoom(est, D, 10, start=22, n_blobs=12)
    assert torch.isfinite(d[-3:]).all()


def test_dpr_reset_mask_touches_only_masked():
    est = _estimator(B=3, n_min=10, radius_px=3.0)
    _run_zoom(est, torch.tensor([-0.2, -0.2, -0.2]), 6, n_blobs=12)
    before = {k: v.clone() for k, v in est.diagnostics().items()}
    window = est.window_image()
    mask = torch.tensor([False, True, False])
    est.reset(mask)
    after = est.diagnostics()
    assert torch.isnan(after["centroids"][1]).all() and after["n_tracked"][1] == 0
    assert after["window_events"][1] == 0 and (est.window_image()[1] == 0).all()
    for k in ("centroids", "n_tracked", "counts", "window_events"):
        assert torch.equal(after[k][~mask].nan_to_num(-1), before[k][~mask].nan_to_num(-1)), k
    assert torch.equal(est.window_image()[~mask], window[~mask])
    # the ring forgets the reset element's old events: after K empty steps its window stays 0
    for k in range(est.n_ring):
        est.update(Events.empty(), (7 + k) * 100_000)
    assert (est.window_image() == 0).all()
    with pytest.raises(ValueError, match="mask"):
        est.reset(torch.tensor([True, False]))


def test_dpr_bad_params():
    with pytest.raises(ValueError, match="n_max"):
        _estimator(n_max=0)
    with pytest.raises(ValueError, match="c_min"):
        _estimator(c_min=1)
    with pytest.raises(ValueError, match="nms_px"):
        _estimator(nms_px=4)
    with pytest.raises(ValueError, match="radius_px"):
        _estimator(radius_px=0.0)


def test_dpr_ring_covers_memory():
    assert _estimator(memory_ms=500.0).n_ring == 5
    assert _estimator(memory_ms=10.0).n_ring == 1


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_dpr_cpu_cuda_agree():
    D = torch.tensor([-0.2, -0.1])
    a = _run_zoom(_estimator(B=2, n_min=10, radius_px=3.0), D, 8, n_blobs=12)
    est = DPREstimator(2, (W, H), device="cuda", dt_s=0.1, n_min=10, radius_px=3.0)
    b = _run_zoom(est, D.cuda(), 8, n_blobs=12).cpu()
    assert torch.allclose(a.nan_to_num(9), b.nan_to_num(9), atol=1e-4)


# ---------------------------------------------------------------- properties
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=40, deadline=None)
@given(scale=st.floats(0.8, 1.25), n=st.integers(2, 15), seed=st.integers(0, 10_000),
       cx=st.floats(0, 127), cy=st.floats(0, 127))
def test_eq8_any_pure_zoom_property(scale, n, seed, cx, cy):
    g = torch.Generator().manual_seed(seed)
    prev = torch.rand(1, n, 2, generator=g, dtype=torch.float64) * 128
    cur = torch.tensor([cx, cy], dtype=torch.float64) + (prev - torch.tensor([cx, cy], dtype=torch.float64)) * scale
    for weighting in ("none", "length"):
        d, k = pairwise_divergence(prev, cur, torch.ones(1, n, dtype=torch.bool), 0.1, weighting=weighting)
        assert k.item() == n * (n - 1) // 2
        assert d.item() == pytest.approx((1 - scale) / 0.1, rel=1e-4, abs=1e-4)


@settings(max_examples=25, deadline=None)
@given(dx=st.integers(-20, 20), dy=st.integers(-20, 20), seed=st.integers(0, 1000))
def test_meanshift_translation_equivariant(dx, dy, seed):
    g = torch.Generator().manual_seed(seed)
    img = torch.zeros(1, 96, 96)
    pts = torch.randint(0, 7, (40, 2), generator=g) + 40
    img[0].index_put_((pts[:, 1], pts[:, 0]), torch.ones(40), accumulate=True)
    seeds = torch.tensor([[[43.3, 42.7]]])
    ok = torch.tensor([[True]])
    c1, n1, _ = meanshift_flat(img, seeds, ok, 4.0, 50, 1e-4)
    shifted = torch.roll(img, shifts=(dy, dx), dims=(1, 2))
    c2, n2, _ = meanshift_flat(shifted, seeds + torch.tensor([dx, dy], dtype=torch.float32), ok, 4.0, 50, 1e-4)
    assert torch.allclose(c2, c1 + torch.tensor([dx, dy], dtype=torch.float32), atol=1e-4)
    assert torch.equal(n1, n2)


# ---------------------------------------------------------------- the multi-step baseline variant
def test_baseline_divergence_exact_for_pure_zoom():
    from dvsland.estimators.divergence import baseline_divergence

    g = torch.Generator().manual_seed(0)
    past = torch.rand(2, 6, 2, generator=g) * 60 - 30
    D, el = -0.25, 0.4
    cur = past * math.exp(-D * el)
    lag = torch.full((2, 6, 6), 4)
    pp = torch.stack([past.unsqueeze(2).expand(-1, -1, 6, -1), past.unsqueeze(1).expand(-1, 6, -1, -1)], 3)
    d, n, rel = baseline_divergence(cur, pp, lag, torch.full((2, 6, 6), el, dtype=torch.float64))
    assert torch.allclose(d, torch.full((2,), D), atol=1e-6) and (n == 15).all() and (rel < 1e-5).all()
    d, n, rel = baseline_divergence(cur, pp, torch.zeros_like(lag), torch.full((2, 6, 6), el, dtype=torch.float64))
    assert torch.isnan(d).all() and (n == 0).all() and torch.isinf(rel).all()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 15), weighting=st.sampled_from(["none", "length"]))
def test_eq8_with_spread_is_pairwise_and_the_one_step_baseline_bit_for_bit(seed, n, weighting):
    """dpr's one-step path computes the pairs' lengths once: Eq. 8 and the baseline spread it gives
    are those of pairwise_divergence and baseline_divergence (lag 1 for the pairs tracked at both
    steps), bit for bit, with untracked (NaN) centroids and coincident ones among them."""
    from dvsland.estimators.divergence import baseline_divergence, eq8_with_spread

    g = torch.Generator().manual_seed(seed)
    B = 4
    prev = torch.rand(B, n, 2, generator=g) * 128
    cur = prev * (1 + 0.05 * torch.rand(B, n, 1, generator=g)) + torch.randn(B, n, 2, generator=g)
    prev[0, 0] = float("nan")
    cur[1, -1] = cur[1, 0]  # a zero-length pair now
    valid = torch.rand(B, n, generator=g) < 0.8
    dt = 0.05 + torch.rand(B, generator=g, dtype=torch.float64) * 0.1
    el = 0.05 + torch.rand(B, generator=g, dtype=torch.float64) * 0.1
    d, k, rel = eq8_with_spread(prev, cur, valid, dt, el, weighting=weighting)
    d_ref, k_ref = pairwise_divergence(prev, cur, valid, dt, weighting=weighting)
    lag = (valid.unsqueeze(2) & valid.unsqueeze(1)).to(torch.int64)
    pp = torch.stack([prev.unsqueeze(2).expand(-1, -1, n, -1), prev.unsqueeze(1).expand(-1, n, -1, -1)], 3)
    rel_ref = baseline_divergence(cur, pp, lag, el.view(-1, 1, 1).expand(-1, n, n).contiguous())[2]
    assert torch.equal(d.nan_to_num(7.0), d_ref.nan_to_num(7.0)) and torch.equal(k, k_ref)
    assert torch.equal(rel, rel_ref)
    with pytest.raises(ValueError, match="weighting must be 'none' or 'length'"):
        eq8_with_spread(prev, cur, valid, dt, el, weighting="median")


def test_dpr_baseline_variant_tracks_zoom_resets_by_mask_and_gives_nan():
    D = torch.tensor([-0.3, -0.15, -0.15])
    est = get_estimator("dpr", 3, (W, H), dt_s=0.1, n_min=10, radius_px=3.0, baseline_steps=5)
    d = _run_zoom(est, D, 15, n_blobs=12)
    med = d[8:].median(0).values
    assert torch.isfinite(d[8:]).all() and torch.allclose(med, D, rtol=0.1), med
    conf = est.confidence()
    assert ((conf > 0) & (conf <= 1)).all()
    est.reset(torch.tensor([False, True, False]))
    d2 = est.update(Events.empty(), 1_600_000)
    assert torch.isnan(d2[1]) and est.confidence()[1] == 0 and est.diagnostics()["n_tracked"][1] == 0
    assert torch.isfinite(d2[[0, 2]]).all()  # the others keep tracking from their window
    with pytest.raises(ValueError, match="baseline_steps"):
        get_estimator("dpr", 1, (W, H), baseline_steps=0)



def test_dpr_hot_pixel_cap_keeps_hot_pixels_out_of_the_centroids():
    """A hot pixel (40 events per step at one pixel) is the densest peak of the window: without the
    cap DPR tracks it as a centroid; with hot_pixel_factor = 4 it is capped below n_min and only the
    zooming blobs (about 60 events each in the window) are tracked (not in paper; off by default)."""
    D = torch.tensor([-0.3])
    offsets = blob_layout(1, 12, (W, H), extent=0.75, seed=3)
    ests = {f: get_estimator("dpr", 1, (W, H), dt_s=0.1, n_min=30, radius_px=3.0, hot_pixel_factor=f) for f in (0, 4)}
    hot = torch.tensor([40.0, 20.0])
    for k in range(8):
        ev = zoom_blob_events(offsets, D, k * 100_000, (k + 1) * 100_000, (W, H), events_per_blob=12, sigma_px=0.6,
                              seed=k)
        n = 40
        t = torch.arange(1, n + 1) * (100_000 // n) + k * 100_000
        ev = Events(torch.cat([ev.b, torch.zeros(n, dtype=torch.long)]), torch.cat([ev.x, torch.full((n,), 40)]),
                    torch.cat([ev.y, torch.full((n,), 20)]), torch.cat([ev.t, t]),
                    torch.cat([ev.p, torch.ones(n, dtype=torch.int8)]), sort=True)
        for est in ests.values():
            est.update(ev, (k + 1) * 100_000)
    near_hot = {f: bool(((e.diagnostics()["centroids"][0] - hot).norm(dim=-1) < 1.5).any()) for f, e in ests.items()}
    assert near_hot == {0: True, 4: False}
    img = ests[4].state.window
    cap = 4 * img.sum() / (img > 0).sum()
    assert float(capped_window(img, 4.0).max()) == pytest.approx(float(cap))


@pytest.mark.parametrize("batch", [1, 2, 5])
@pytest.mark.parametrize("shape", [(128, 128), (31, 45)])
def test_dpr_blur_equals_kornia(batch, shape):
    """The DPR blur (one depthwise convolution over the batch) gives kornia's gaussian blur
    (filter2d_separable, zero border) of a batch bit for bit; one image as kornia blurs it beside
    another (kornia's blur of a single image alone sums in another order on some CPUs)."""
    import kornia

    from dvsland.estimators.density_peaks import _blur_depthwise, _gaussian_kernels

    g = torch.Generator().manual_seed(batch)
    img = torch.poisson(torch.rand(batch, *shape, generator=g) * 0.7, generator=g)
    kx, ky = _gaussian_kernels(13, 2.0, "cpu", torch.float32)
    two = img.expand(max(batch, 2), -1, -1).unsqueeze(1)
    ref = kornia.filters.gaussian_blur2d(two, (13, 13), (2.0, 2.0), border_type="constant")[:batch, 0]
    out = _blur_depthwise(img, kx, ky)
    assert out.shape == img.shape
    assert torch.equal(out, ref)


def _meanshift_both(pad, seeds, valid, radius, tol, q):
    from dvsland.estimators import native_dpr

    out = []
    for on in (True, False):
        native_dpr.use_native_dpr(on)
        try:
            out.append(meanshift_flat(pad, seeds, valid, radius, 20, tol, image_pad_px=q))
        finally:
            native_dpr.use_native_dpr(None)
    return out


@pytest.mark.parametrize("seed", range(6))
def test_meanshift_compiled_equals_torch_path(seed):
    """The compiled mean-shift (dvsland.estimators.native_dpr, built here where a compiler is found)
    gives the torch path's centroids, counts and iterations bit for bit on whole-number counts."""
    from dvsland.estimators import native_dpr

    if native_dpr._LIB.load(force=True) is None:
        pytest.skip("no C++ compiler here")
    g = torch.Generator().manual_seed(seed)
    B, N, H, W = 3, 12, 40 + seed, 50 - seed
    radius = [4.0, 2.5, 0.7, 5.3, 3.0, 1.0][seed]
    q = math.ceil(radius) + 1 + seed % 2
    img = torch.poisson(torch.rand(B, H, W, generator=g) * 2.0, generator=g)
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    img += (25 * torch.exp(-((xx - W / 3) ** 2 + (yy - H / 2) ** 2) / 15.0)).round()
    pad = torch.nn.functional.pad(img, (q,) * 4)
    seeds = torch.rand(B, N, 2, generator=g) * torch.tensor([W + 4.0, H + 4.0]) - 2
    valid = torch.rand(B, N, generator=g) < 0.8
    seeds[~valid] = float("nan")
    for tol in (0.01, 0.0):
        (c1, n1, i1), (c0, n0, i0) = _meanshift_both(pad, seeds, valid, radius, tol, q)
        assert torch.equal(c1.nan_to_num(-7), c0.nan_to_num(-7)) and torch.equal(n1, n0) and int(i1) == int(i0)
        assert torch.isfinite(c1).any()


def test_meanshift_fractional_counts_take_the_torch_path():
    """Counts that are not whole numbers (the hot-pixel cap) make the kernel decline: the torch path's result."""
    from dvsland.estimators import native_dpr

    kern = native_dpr._LIB.load(force=True)
    if kern is None:
        pytest.skip("no C++ compiler here")
    img = torch.zeros(1, 20, 20)
    img[0, 9:12, 9:12] = 2.5
    pad = torch.nn.functional.pad(img, (5,) * 4)
    seeds, valid = torch.tensor([[[9.0, 10.0]]]), torch.tensor([[True]])
    assert kern.meanshift(pad, 5, 20, 20, seeds, valid, 4.0, 20, 0.01) is None
    (c1, n1, _), (c0, n0, _) = _meanshift_both(pad, seeds, valid, 4.0, 0.01, 5)
    assert torch.equal(c1, c0) and torch.equal(n1, n0) and torch.allclose(c0, torch.tensor([[[10.0, 10.0]]]))


def _peaks_both(img, n_max, sigma, nms):
    from dvsland.estimators import native_dpr
    from dvsland.estimators.density_peaks import density_peaks

    out = []
    for on in (True, False):
        native_dpr.use_native_dpr(on)
        try:
            out.append(density_peaks(img, n_max, sigma, nms))
        finally:
            native_dpr.use_native_dpr(None)
    return out


@pytest.mark.parametrize("batch,shape,sigma,nms", [(18, (128, 128), 2.0, 3), (2, (31, 45), 1.0, 5),
                                                    (5, (130, 97), 3.0, 1), (1, (64, 200), 2.0, 3)])
def test_density_peaks_compiled_equal_the_torch_path(batch, shape, sigma, nms, count_calls):
    """DPR's compiled blur, local maxima and scores (dvsland.estimators.native_dpr) give the torch
    path's peaks, densities and validity bit for bit (oneDNN's depthwise sums, one image as the first of
    two), and the compiled pass ran where it matches this machine's torch path."""
    from dvsland.estimators import density_peaks as dp
    from dvsland.estimators import native_dpr

    kern = native_dpr._LIB.load(force=True)
    if kern is None:
        pytest.skip("no C++ compiler here")
    g = torch.Generator().manual_seed(batch)
    img = torch.poisson(torch.rand(batch, *shape, generator=g) * 0.8, generator=g)
    img[:, :, : shape[1] // 3] = 0.0  # an empty band: no peaks there
    calls = count_calls(native_dpr.Kernels, "peak_scores")
    (p1, d1, v1), (p0, d0, v0) = _peaks_both(img, 15, sigma, nms)
    assert torch.equal(p1.nan_to_num(-7), p0.nan_to_num(-7)) and torch.equal(d1, d0) and torch.equal(v1, v0)
    assert v1.any()
    assert bool(calls) == dp.compiled_scores_match(kern)


@pytest.mark.parametrize("native", [True, False])
def test_an_images_peaks_do_not_depend_on_the_images_blurred_with_it(native):
    """DPR re-initialises only the descents that need it, one or several at a time: an image's blur,
    peaks and densities are the same bits alone as within any batch, on the compiled and the torch path."""
    from dvsland.estimators import native_dpr
    from dvsland.estimators.density_peaks import density_peaks

    g = torch.Generator().manual_seed(7)
    img = torch.poisson(torch.rand(5, 128, 128, generator=g) * 0.3, generator=g)
    native_dpr.use_native_dpr(native)
    try:
        whole = density_peaks(img, 15, 2.0, 3)
        for sel in ([0], [3], [1, 2], [4, 0, 2]):
            part = density_peaks(img[sel], 15, 2.0, 3)
            for a, b in zip(part, whole):
                assert torch.equal(a.nan_to_num(-7), b[sel].nan_to_num(-7))
    finally:
        native_dpr.use_native_dpr(None)


def test_density_peaks_compiled_scores_are_checked_against_torch():
    """The compiled scores are used only after a sample matched the torch path on this machine;
    a kernel that sums in another order is refused (the torch path runs)."""
    from dvsland.estimators import density_peaks as dp
    from dvsland.estimators import native_dpr

    kern = native_dpr._LIB.load(force=True)
    if kern is None:
        pytest.skip("no C++ compiler here")
    assert dp.compiled_scores_match(kern)  # oneDNN's depthwise convolution: the fused chain

    class Unfused:  # rounded products added in tap order (a plain convolution's sums on many CPUs): refused
        def peak_scores(self, img, kx, ky, nms_px, min_density):
            k, r = kx.shape[-1], kx.shape[-1] // 2
            x = torch.nn.functional.pad(img, (r, r, r, r))
            h = torch.zeros(img.shape[0], img.shape[1] + 2 * r, img.shape[2])
            for t in range(k):
                h = h + x[:, :, t:t + img.shape[2]] * kx[0, t]
            blurred = torch.zeros_like(img)
            for t in range(k):
                blurred = blurred + h[:, t:t + img.shape[1]] * ky[0, t]
            is_peak = (blurred >= dp._max_filter(blurred, nms_px)) & (blurred > min_density)
            return blurred, torch.where(is_peak, blurred, torch.full_like(blurred, -1.0))

    assert not dp.compiled_scores_match(Unfused())

    class Float64Sums:  # the same blur summed in float64, rounded once: other bits on some pixels
        def peak_scores(self, img, kx, ky, nms_px, min_density):
            blurred = dp._blur_depthwise(img.double(), kx.double(), ky.double()).float()
            is_peak = (blurred >= dp._max_filter(blurred, nms_px)) & (blurred > min_density)
            return blurred, torch.where(is_peak, blurred, torch.full_like(blurred, -1.0))

    assert not dp.compiled_scores_match(Float64Sums())
    with pytest.raises(RuntimeError, match="peak_scores: img"):
        kern.peak_scores(torch.zeros(2, 5, 5, dtype=torch.float64), *dp._gaussian_kernels(7, 1.0, "cpu",
                                                                                         torch.float32), 3, 0.0)
