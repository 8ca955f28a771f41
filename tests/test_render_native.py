"""The fast renderer's compiled sampling passes (dvsland.render.native_render): the same frames as
the torch path (bit for bit where torch runs its AVX2 / AVX-512 kernels), every branch of the pass
(per-pixel and per-frame ranges, shared and per-site gains, threads, nearest level), input checks,
and the mode switch."""

from __future__ import annotations

import pytest
import torch

from dvsland.config import CameraConfig, RenderConfig
from dvsland.render import native_render
from dvsland.render.fast import FastRenderer

CAM = CameraConfig(width_px=48, height_px=48, fov_deg=60.0)
SITES = ["A", "E", "G", "H"]


@pytest.fixture(scope="module")
def kernels(native_kernels):
    return native_kernels(native_render.LIBRARY, "the compiled render passes")


def _same(a: torch.Tensor, b: torch.Tensor) -> None:
    """Equal to the bit where torch's grid_sampler is its vectorised (contracted) kernel, else to rounding."""
    if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"):
        assert torch.equal(a, b), f"{int((a != b).sum())} of {a.numel()} pixels differ"
    else:
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def _pair(**kw):
    rc = kw.pop("render", RenderConfig(threads=1))
    sites = kw.pop("sites", SITES)
    cam = kw.pop("camera", CAM)
    return (FastRenderer(sites, cam, rc, disk_cache=False, native=False, **kw),
            FastRenderer(sites, cam, rc, disk_cache=False, native=True, **kw))


def _altitudes(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    alt = torch.exp(torch.empty(n).uniform_(2.31, 9.9, generator=g))  # 10.1 m ... 19.9 km, log-uniform
    return alt, torch.randint(0, len(SITES), (n,), generator=g)


def test_frames_identical_to_torch_path(kernels):
    """Random altitudes and sites over the whole range, a batch that is not a multiple of the chunk."""
    torch_r, native_r = _pair()
    alt, idx = _altitudes(70)
    _same(torch_r.render(alt, idx), native_r.render(alt, idx))


@pytest.mark.parametrize("case", ["no_parallax", "two_parallax", "nearest_level", "threads", "per_site_gain",
                                  "odd_sensor", "wide_sensor"])
def test_every_branch_identical_to_torch_path(kernels, case):
    kw = {"no_parallax": dict(parallax_iters=0), "two_parallax": dict(parallax_iters=2),
          "nearest_level": dict(blend_levels=False), "threads": dict(threads=3),
          "per_site_gain": dict(sites=["A", "E"], suns=[(12.0, 0.0), (18.0, 5.0)]),
          "odd_sensor": dict(camera=CameraConfig(width_px=35, height_px=27, fov_deg=60.0)),  # full-size relief
          "wide_sensor": dict(camera=CameraConfig(width_px=64, height_px=36, fov_deg=60.0))}[case]
    torch_r, native_r = _pair(**kw)
    if case == "per_site_gain":
        assert native_r._gain_shared is None  # the gains differ: read per frame by site
    alt, idx = _altitudes(23, seed=1)
    idx = idx % len(native_r.site_names)
    _same(torch_r.render(alt, idx), native_r.render(alt, idx))


def test_kernel_is_used_and_mode_off_runs_torch(kernels, monkeypatch, count_calls):
    _, native_r = _pair()
    calls = count_calls(native_render.Kernels, "levels")
    alt, idx = _altitudes(5)
    native_r.render(alt, idx)
    assert calls == [1]
    monkeypatch.setattr(native_render.LIBRARY, "chosen", False)
    assert native_render.kernel_for(alt) is None
    native_r.render(alt, idx)
    assert calls == [1]


def test_kernel_checks_its_inputs(kernels):
    plain = torch.rand(64, 128)
    atlas = native_render.tile_atlas(plain)
    off = torch.zeros(4, 2)
    slopes = torch.zeros(2, 3, 4, 4)
    rng, frac, gain, out = torch.ones(2), torch.zeros(2), torch.ones(4, 4), torch.empty(2, 4, 4)
    kernels.levels(atlas, off, slopes, torch.tensor([0, 2]), rng, frac, gain, out)
    assert torch.isfinite(out).all()
    with pytest.raises(RuntimeError, match="site index"):
        kernels.levels(atlas, off, slopes, torch.tensor([0, 3]), rng, frac, gain, out)
    with pytest.raises(RuntimeError, match="atlas must be a contiguous torch.float32 CPU tensor"):
        kernels.levels(atlas._replace(texels=atlas.texels.double()), off, slopes, torch.tensor([0, 1]), rng, frac,
                       gain, out)
    with pytest.raises(RuntimeError, match="atlas must be a TiledAtlas"):
        kernels.levels(plain, off, slopes, torch.tensor([0, 1]), rng, frac, gain, out)
    T = native_render.TILE_TEXELS
    with pytest.raises(RuntimeError, match=f"atlas must hold {(64 // T + 1) * (128 // T) * T * T} elements"):
        kernels.levels(atlas._replace(height=64 + T), off, slopes, torch.tensor([0, 1]), rng, frac, gain, out)
    with pytest.raises(RuntimeError, match="off must hold 8 elements"):
        kernels.levels(atlas, off[:3], slopes, torch.tensor([0, 1]), rng, frac, gain, out)
    with pytest.raises(RuntimeError, match="site_idx"):
        kernels.relief(atlas, off[:2], slopes, torch.tensor([0]), torch.ones(2), torch.ones(2), torch.ones(2), 1)


def test_relief_matches_its_definition(kernels):
    """On a constant height field h the ranges are max(z - h, 0.05 z) times inv_lo, whatever the slopes."""
    atlas = native_render.tile_atlas(torch.full((32, 64), 30.0))
    slopes = torch.randn(2, 2, 6, 6)
    z = torch.tensor([100.0, 20.0, 500.0])
    inv_lo = torch.tensor([1.0, 0.5, 0.25])
    r = kernels.relief(atlas, torch.zeros(2, 3), slopes, torch.tensor([0, 1, 1]), z, torch.ones(3), inv_lo, 2)
    want = torch.maximum(z - 30.0, 0.05 * z) * inv_lo
    assert r.shape == (3, 6, 6) and torch.equal(r, want[:, None, None].expand(3, 6, 6))


@pytest.mark.parametrize("hw", [(6, 6), (5, 9), (1, 4), (3, 1), (64, 64)])
def test_relief_upsampled_in_its_pass_equals_upsample2x(kernels, hw):
    """``upsample2x=True`` gives :func:`dvsland.render.fast._upsample2x` of the plain ranges, bit for bit
    (a varying height field, so the ranges differ from point to point; edges and 1-wide fields)."""
    from dvsland.render.fast import _upsample2x

    h, w = hw
    g = torch.Generator().manual_seed(3)
    atlas = native_render.tile_atlas(torch.rand(32, 64, generator=g) * 40.0)
    slopes = torch.randn(2, 2, h, w, generator=g) * 0.3
    z = torch.tensor([100.0, 20.0, 500.0])
    inv, inv_lo = torch.tensor([0.01, 0.05, 0.002]), torch.tensor([1.0, 0.5, 0.25])
    args = (atlas, torch.zeros(2, 3), slopes, torch.tensor([0, 1, 1]), z, inv, inv_lo, 2)
    plain = kernels.relief(*args)
    up = kernels.relief(*args, upsample2x=True)
    assert up.shape == (3, 2 * h, 2 * w) and plain.unique().numel() > 3
    assert torch.equal(up, _upsample2x(plain))


def test_atlas_too_large_for_int32_indices_is_left_to_torch():
    """2^31 texels or more (about 1,100 dispersed scenes) cannot be indexed by the passes: the renderer
    then samples with grid_sample (checked on meta tensors: no memory)."""
    assert native_render.fits(torch.empty(388 * 9, 388 * 13))
    assert native_render.fits(native_render.TiledAtlas(torch.empty(0), 388 * 9, 388 * 13))
    assert not native_render.fits(native_render.TiledAtlas(torch.empty(0), 388 * 1100, 388 * 13))
    assert not native_render.fits(torch.empty(388 * 1100, 388 * 13, device="meta"))
    assert not native_render.fits(torch.empty(10, 1))


@pytest.mark.parametrize("hw", [(1, 2), (15, 17), (32, 32), (33, 5), (40, 96), (388, 5044)])
def test_tiled_atlas_is_the_atlas_in_square_tiles(hw):
    """tile_atlas: the texels tile after tile, each tile row-major, zero padding (sizes that are and are
    not multiples of the tile, narrower and shorter than a tile); untile_atlas gives the atlas back."""
    h, w = hw
    atlas = torch.rand(h, w, generator=torch.Generator().manual_seed(h * w))
    tiled = native_render.tile_atlas(atlas)
    T = native_render.TILE_TEXELS
    ht, wt = -(-h // T), -(-w // T)
    want = torch.nn.functional.pad(atlas, (0, wt * T - w, 0, ht * T - h)).view(ht, T, wt, T).permute(0, 2, 1, 3)
    assert (tiled.height, tiled.width) == (h, w) and torch.equal(tiled.texels, want.reshape(-1))
    assert torch.equal(native_render.untile_atlas(tiled), atlas)
    with pytest.raises(ValueError, match="tile_atlas: atlas must be a"):
        native_render.tile_atlas(atlas.double())


def test_renderer_holds_one_layout_and_switches_with_the_mode(kernels, monkeypatch):
    """The compiled passes read the atlases in tiles, the torch path row-major: the renderer builds the
    layout its mode will read, converts when the mode changes, keeps one layout, and gives the same
    frames either way."""
    torch_r, native_r = _pair()
    assert native_r._atlas_tiled and isinstance(native_r._atlas_pair[0], native_render.TiledAtlas)
    t, k = torch_r.levels.tile_size, torch_r.levels.n_levels
    assert not torch_r._atlas_tiled and torch_r._atlas_pair[0].shape == (1, 1, t * len(SITES), t * k)
    alt, idx = _altitudes(9, seed=4)
    ref = torch_r.render(alt, idx)
    _same(ref, native_r.render(alt, idx))
    assert native_r._atlas_tiled
    assert torch.equal(native_r.atlas_irradiance, torch_r.atlas_irradiance)  # converted back: the same texels
    assert not native_r._atlas_tiled and torch.equal(native_r.render(alt, idx), ref)  # the torch path's layout
    _same(ref, native_r.render(alt, idx))
    assert native_r._atlas_tiled
    monkeypatch.setattr(native_render.LIBRARY, "chosen", False)  # the mode off: the torch path, row-major
    assert torch.equal(native_r.render(alt, idx), ref) and not native_r._atlas_tiled


@pytest.mark.parametrize("y0, x0, hw", [(0, 0, (40, 96)), (5, 7, (30, 60)), (31, 33, (1, 1)), (64, 0, (36, 96))])
def test_tiled_write_places_a_block(y0, x0, hw):
    """A block written at any offset (inside one tile, across tile edges, at the atlas's last row) lands
    where the row-major atlas has it; the padding stays 0."""
    h, w = hw
    full = torch.zeros(100, 96)
    full[y0:y0 + h, x0:x0 + w] = torch.rand(h, w)
    tiled = native_render.tiled_empty(100, 96)  # its padding 0, the rest written below
    native_render.tiled_write(tiled, 0, 0, torch.zeros(100, 96))
    native_render.tiled_write(tiled, y0, x0, full[y0:y0 + h, x0:x0 + w])
    assert torch.equal(tiled.texels, native_render.tile_atlas(full).texels)
    with pytest.raises(ValueError, match="outside the atlas"):
        native_render.tiled_write(tiled, 90, 0, torch.zeros(11, 4))
