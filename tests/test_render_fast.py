"""The fast renderer: interface, errors, determinism, features, agreement with the terrain."""

from __future__ import annotations

import math

import pytest
import torch

from dvsland.config import CameraConfig, RenderConfig
from dvsland.render import FastRenderer, Renderer, available_renderers, get_renderer
from dvsland.render import lod as lod_mod

CAM = CameraConfig(width_px=48, height_px=48, fov_deg=60.0)


@pytest.fixture(scope="module")
def renderer():
    # small sensor: cheap preparation; no disk cache so the test sees a fresh computation
    return get_renderer("fast", ["A", "E", "G", "H"], CAM, RenderConfig(), disk_cache=False)


def test_registry():
    assert {"fast", "pyrender"} <= set(available_renderers())
    with pytest.raises(ValueError, match="unknown renderer"):
        get_renderer("raytracer", ["A"], CAM)


def test_smoke_shapes_dtype(renderer):
    assert isinstance(renderer, Renderer) and isinstance(renderer, FastRenderer)
    alt = torch.tensor([20000.0, 5000.0, 1000.0, 200.0, 50.0, 10.0])
    idx = torch.tensor([0, 1, 2, 3, 0, 1])
    f = renderer.render(alt, idx)
    assert f.shape == (6, 48, 48) and f.dtype == torch.float32
    assert torch.isfinite(f).all() and (f > 0).all()
    assert renderer.render(alt[:0], idx[:0]).shape == (0, 48, 48)


def test_levels_cover_range(renderer):
    p = renderer.levels
    assert p.level_size >= 2 * math.sqrt(2) * 48
    lam = renderer.lod(torch.tensor([10.0, 20000.0]))
    assert float(lam[0]) == 0.0 and float(lam[1]) <= p.n_levels - 1


@pytest.mark.parametrize("alt", [9.0, 20001.0, float("nan"), float("inf")])
def test_altitude_out_of_range(renderer, alt):
    with pytest.raises(ValueError, match=r"altitude_m .*\[10.0, 20000.0\]"):
        renderer.render(torch.tensor([100.0, alt]), torch.tensor([0, 0]))


def test_bad_site_index_and_shapes(renderer):
    with pytest.raises(ValueError, match=r"site_idx .*\[0, 3\]"):
        renderer.render(torch.tensor([100.0]), torch.tensor([4]))
    with pytest.raises(ValueError, match="site_idx"):
        renderer.render(torch.tensor([100.0]), torch.tensor([-1]))
    with pytest.raises(ValueError, match="shape"):
        renderer.render(torch.tensor([[100.0]]), torch.tensor([[0]]))
    with pytest.raises(ValueError, match="integer"):
        renderer.render(torch.tensor([100.0]), torch.tensor([0.0]))


def test_unknown_site_name():
    with pytest.raises(ValueError, match="unknown site 'Q'"):
        get_renderer("fast", ["A", "Q"], CAM)


def test_batch_elements_independent(renderer):
    alt = torch.tensor([3000.0, 120.0, 15.0])
    idx = torch.tensor([1, 2, 0])
    f = renderer.render(alt, idx)
    for k in range(3):
        torch.testing.assert_close(renderer.render(alt[k:k + 1], idx[k:k + 1])[0], f[k])


def test_chunking_is_invisible(renderer):
    alt = torch.tensor([3000.0, 120.0, 15.0, 800.0, 60.0])
    idx = torch.tensor([1, 2, 0, 3, 1])
    whole = renderer.render(alt, idx)
    renderer.chunk, old = 2, renderer.chunk
    try:
        torch.testing.assert_close(renderer.render(alt, idx), whole)
    finally:
        renderer.chunk = old


def test_sub_batches_stop_growing_with_the_batch(renderer):
    """Up to 32 x chunk frames a render call takes at most 8 sub-batches (of up to 4 x chunk frames):
    its operator calls (cProfile) are the same at 8 x chunk and 32 x chunk frames, and the frames are
    bit for bit those of one sub-batch, an uneven last one included."""
    import cProfile
    import pstats

    from dvsland.render.fast import sub_batch

    assert [sub_batch(b, 32) for b in (1, 63, 256, 257, 576, 1024, 5000)] == [32, 32, 32, 33, 72, 128, 128]
    g = torch.Generator().manual_seed(0)
    renderer.chunk, old = 2, renderer.chunk
    try:
        def calls(b):
            alt = 20.0 + 3000.0 * torch.rand(b, generator=g, dtype=torch.float64)
            idx = torch.randint(0, 4, (b,), generator=g)
            renderer.render(alt, idx)  # warm
            prof = cProfile.Profile()
            prof.enable()
            frames = renderer.render(alt, idx)
            prof.disable()
            renderer.chunk = 1000
            try:
                assert torch.equal(frames, renderer.render(alt, idx))
            finally:
                renderer.chunk = 2
            return pstats.Stats(prof).total_calls

        assert calls(16) == calls(64)
        assert calls(61) <= calls(64) + 8  # 8 sub-batches, the last one shorter (its own grid buffer)
    finally:
        renderer.chunk = old


def test_preparation_deterministic(monkeypatch):
    """Same seed -> the same levels bit for bit (fresh computation, no caches)."""
    from dvsland.terrain import load_site

    params = lod_mod.LevelParams(level_size=32, base_texel_m=1.0, n_levels=3)
    monkeypatch.setattr(lod_mod, "_MEMORY", {})
    a = lod_mod.prepare_levels(load_site("D"), params, disk_cache=False)
    monkeypatch.setattr(lod_mod, "_MEMORY", {})
    b = lod_mod.prepare_levels(load_site("D"), params, disk_cache=False)
    assert a.source == b.source == "computed"
    assert torch.equal(a.irradiance, b.irradiance) and torch.equal(a.height_m, b.height_m)


def test_disk_cache_roundtrip(monkeypatch, tmp_path):
    from dvsland.terrain import load_site

    monkeypatch.setenv("DVSLAND_CACHE_DIR", str(tmp_path))
    params = lod_mod.LevelParams(level_size=16, base_texel_m=2.0, n_levels=2)
    monkeypatch.setattr(lod_mod, "_MEMORY", {})
    a = lod_mod.prepare_levels(load_site("B"), params)
    monkeypatch.setattr(lod_mod, "_MEMORY", {})
    b = lod_mod.prepare_levels(load_site("B"), params)
    assert (a.source, b.source) == ("computed", "disk")
    assert torch.equal(a.irradiance, b.irradiance)


def _log_std(f):
    return torch.log(f).flatten(1).std(dim=1)


def test_features_visible_at_every_altitude(renderer):
    """Contrast (std of log irradiance) at 5 km, 1 km, 200 m, 50 m: A, E, G well above H."""
    alts = torch.tensor([5000.0, 1000.0, 200.0, 50.0])
    s_h = _log_std(renderer.render(alts, torch.full((4,), 3)))
    assert (s_h < 0.03).all(), s_h  # H: flat and dusty
    for k, floor in ((0, 0.1), (1, 0.1), (2, 0.04)):  # A, E craters; G rocky with few craters
        s = _log_std(renderer.render(alts, torch.full((4,), k)))
        assert (s > floor).all() and (s > 2 * s_h).all(), (k, s)


def test_shadows_present(renderer):
    """Cast shadows: a visible fraction of pixels near the ambient floor on cratered sites."""
    f = renderer.render(torch.tensor([5000.0, 1000.0]), torch.tensor([0, 1]))
    med = f.flatten(1).median(dim=1).values[:, None]
    frac_dark = (f.flatten(1) < 0.25 * med).float().mean(dim=1)
    assert (frac_dark > 0.002).all(), frac_dark


def test_matches_terrain_irradiance(renderer):
    """A frame (no parallax) matches the terrain's own shaded map of the footprint."""
    from dvsland.terrain import load_site

    r0 = get_renderer("fast", ["E"], CAM, RenderConfig(), disk_cache=False, parallax_iters=0)
    for alt in (2000.0, 150.0):
        f = r0.render(torch.tensor([alt]), torch.tensor([0]))[0]
        ref = load_site("E").irradiance(r0.footprint_m(alt), 48)
        a, b = torch.log(f).flatten(), torch.log(ref).flatten()
        corr = torch.corrcoef(torch.stack([a, b]))[0, 1]
        assert corr > 0.85, (alt, corr)


def test_parallax_moves_low_frames_only(renderer):
    r0 = get_renderer("fast", ["G"], CAM, RenderConfig(), disk_cache=False, parallax_iters=0)
    r1 = get_renderer("fast", ["G"], CAM, RenderConfig(), disk_cache=False, parallax_iters=1)
    lo = torch.tensor([15.0])
    hi = torch.tensor([8000.0])
    i0 = torch.tensor([0])
    d_lo = (torch.log(r0.render(lo, i0)) - torch.log(r1.render(lo, i0))).abs().mean()
    d_hi = (torch.log(r0.render(hi, i0)) - torch.log(r1.render(hi, i0))).abs().mean()
    assert d_lo > 0.01 and d_lo > 3 * d_hi


def test_zoom_is_smooth(renderer):
    """Pure zoom: consecutive frame-to-frame log changes rarely reverse sign (no LOD flicker)."""
    z = torch.tensor([1000.0 * 0.98 ** k for k in range(12)])
    f = torch.log(renderer.render(z, torch.zeros(12, dtype=torch.long)))
    d = f[1:] - f[:-1]
    both = (d[1:].abs() > 1e-3) & (d[:-1].abs() > 1e-3)
    rev = ((d[1:] * d[:-1]) < 0) & both
    assert float(rev.sum() / both.sum().clamp(min=1)) < 0.15


def test_cuda_matches_cpu():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    rc = get_renderer("fast", ["A"], CAM, disk_cache=False)
    rg = get_renderer("fast", ["A"], CAM, disk_cache=False, device="cuda")
    alt, idx = torch.tensor([4000.0, 60.0]), torch.tensor([0, 0])
    torch.testing.assert_close(rg.render(alt, idx).cpu(), rc.render(alt, idx), rtol=1e-4, atol=1e-6)


def test_property_finite_positive(renderer):
    """Any altitude in range and any site: finite, positive frames (hypothesis)."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=25, deadline=None)
    @given(st.lists(st.tuples(st.floats(10.0, 20000.0), st.integers(0, 3)), min_size=1, max_size=6))
    def check(items):
        alt = torch.tensor([a for a, _ in items], dtype=torch.float32)
        idx = torch.tensor([i for _, i in items])
        f = renderer.render(alt, idx)
        assert f.shape == (len(items), 48, 48)
        assert torch.isfinite(f).all() and (f > 0).all()

    check()


@pytest.mark.slow
def test_all_sites_full_camera_contrast():
    """Paper camera (128 px, 60 deg): A-G show features at 5 km, 1 km, 200 m, 50 m; H and I are
    far flatter (std of log irradiance)."""
    r = get_renderer("fast", list("ABCDEFGHI"), CameraConfig(), RenderConfig())
    alts = torch.tensor([5000.0, 1000.0, 200.0, 50.0]).repeat_interleave(9)
    idx = torch.arange(9).repeat(4)
    s = _log_std(r.render(alts, idx)).view(4, 9)
    assert (s[:, :7] > 0.08).all(), s
    assert (s[:, 7] < 0.03).all(), s
    assert (s[:, 7] < s[:, :7].min(dim=1).values / 2).all(), s


def test_threads_split_is_exact_and_restores_torch_threads(renderer):
    """Sampling split over threads gives the same frames bit for bit, and a render call leaves
    the caller's torch thread count as it was."""
    r1 = get_renderer("fast", ["A", "E", "G", "H"], CAM, RenderConfig(threads=1), disk_cache=False)
    r3 = get_renderer("fast", ["A", "E", "G", "H"], CAM, RenderConfig(), disk_cache=False, threads=3)
    assert r1.threads == 1 and r3.threads == 3
    alt = torch.tensor([60.0, 900.0, 4000.0, 9000.0, 300.0, 75.0])
    idx = torch.tensor([0, 1, 2, 3, 1, 0])
    before = torch.get_num_threads()
    a, b = r1.render(alt, idx), r3.render(alt, idx)
    assert torch.get_num_threads() == before
    assert torch.equal(a, b)


def test_threads_bad_value():
    with pytest.raises(ValueError, match="threads"):
        get_renderer("fast", ["A"], CAM, disk_cache=False, threads=-1)


def test_terrain_preparation_shows_progress(capsys, monkeypatch):
    """With progress on, each prepared scene advances a bar on stderr (the first run prepares terrain
    for a minute: the user sees it move)."""
    monkeypatch.setenv("DVSLAND_CACHE_DIR", "off")
    from dvsland.config import CameraConfig, RenderConfig
    from dvsland.render.fast import FastRenderer

    FastRenderer(["E"], CameraConfig(width_px=32, height_px=32), RenderConfig(threads=1), disk_cache=False,
                 progress=True)
    err = capsys.readouterr().err
    assert "terrain" in err and "1/1" in err and "scene=E" in err
