"""Terrain: site specs, determinism, band-limited sampling, photometry and shadows."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dvsland.terrain import (Grid, SiteSpec, Terrain, available_sites, cast_shadow, load_site, load_spec,
                             lunar_lambert_l, shade, spec_from_dict)


def test_nine_sites_shipped():
    assert available_sites() == list("ABCDEFGHI")
    for name in "ABCDEFGHI":
        spec = load_spec(name)
        assert spec.name == name and 10 <= spec.sun.elevation_deg <= 20


def test_unknown_site_lists_names():
    with pytest.raises(ValueError, match="A, B, C, D, E, F, G, H, I"):
        load_site("Z")


def test_bad_spec_value_named():
    with pytest.raises(ValueError, match="craters.density"):
        spec_from_dict({"craters": {"density": -1.0}})
    with pytest.raises(ValueError, match="unknown key"):
        spec_from_dict({"crater": {}})


def test_sun_direction_unit_and_override():
    t = load_site("A")
    d = t.sun_direction
    assert d.shape == (3,) and d.dtype == np.float64
    assert abs(np.linalg.norm(d) - 1) < 1e-12
    assert math.isclose(math.degrees(math.asin(d[2])), 15.0, rel_tol=1e-9)
    t30 = load_site("A", sun_elevation_deg=30.0)
    assert math.isclose(t30.sun_direction[2], 0.5, rel_tol=1e-9)
    with pytest.raises(ValueError, match="elevation"):
        load_site("A", sun_elevation_deg=0.0)


def test_heightmap_shape_dtype_device(device):
    h, a = load_site("E").heightmap(400.0, 64, device=device, dtype=torch.float64)
    assert h.shape == (64, 64) and a.shape == (64, 64)
    assert h.dtype == torch.float64 and h.device.type == device.type
    assert torch.isfinite(h).all() and (a > 0).all() and (a <= 1).all()


def test_heightmap_deterministic_bit_for_bit():
    spec = load_spec("D")
    h1, a1 = Terrain(spec).heightmap(300.0, 96, center_xy_m=(12.0, -7.0))
    h2, a2 = Terrain(spec).heightmap(300.0, 96, center_xy_m=(12.0, -7.0))
    assert torch.equal(h1, h2) and torch.equal(a1, a2)


def test_different_seed_different_terrain():
    spec = load_spec("A")
    other = SiteSpec(**{**spec.__dict__, "seed": spec.seed + 1})
    h1, _ = Terrain(spec).heightmap(2000.0, 64)
    h2, _ = Terrain(other).heightmap(2000.0, 64)
    assert not torch.allclose(h1, h2)


def test_continuity_across_grids():
    """The terrain is continuous: two grids sharing texel centres agree there."""
    t = load_site("B")
    h_full, _ = t.heightmap(200.0, 64)
    # the right half of the same grid: centre shifted east by a quarter extent
    h_half, _ = t.heightmap(100.0, 32, center_xy_m=(50.0, 0.0))
    # same spacing (200/64 = 100/32), rows 16..47 of the full grid are the half grid's rows
    assert torch.allclose(h_full[16:48, 32:], h_half, atol=1e-4)


def test_map_view_orientation():
    """Row 0 is north, column 0 is west: a grid centred north-east sees the same values."""
    t = load_site("C")
    h, _ = t.heightmap(100.0, 10)
    h_ne, _ = t.heightmap(20.0, 2, center_xy_m=(40.0, 40.0))  # texels at x, y = 35, 45
    assert torch.allclose(h_ne, h[0:2, 8:10], atol=1e-4)
    g = Grid.centered((0.0, 0.0), 10, 10, 10.0)
    x, y = g.coords()
    assert x[0, 0] < x[0, -1] and y[0, 0] > y[-1, 0]
    assert math.isclose(float(x[0, 0]), -45.0) and math.isclose(float(y[0, 0]), 45.0)


def test_landing_point_clear_of_large_craters():
    for name in "ABCDEFG":
        t = load_site(name)
        big = t.craters.d_m >= t.spec.landing_clear_d_m
        r = torch.hypot(t.craters.x_m, t.craters.y_m)
        assert not bool((big & (r < 0.75 * t.craters.d_m)).any())


def test_crater_size_frequency_is_power_law():
    t = load_site("A")
    d = t.craters.d_m.numpy()
    x, y = t.craters.x_m.numpy(), t.craters.y_m.numpy()
    # count in a window where every octave up to 8 m is complete (region 256 D >= window)
    inside = (np.abs(x) < 50) & (np.abs(y) < 50)
    n1 = np.sum(inside & (d >= 1.0))
    n4 = np.sum(inside & (d >= 4.0))
    slope = math.log(n1 / n4) / math.log(4.0)
    assert 1.6 < slope < 2.4, slope  # N(>D) ~ D^-2


def test_features_small_sites_rank():
    """H is flat and featureless compared with a cratered site at the same scale."""
    ha, _ = load_site("A").heightmap(500.0, 128)
    hh, _ = load_site("H").heightmap(500.0, 128)
    assert float(ha.std()) > 3 * float(hh.std())


def test_band_limit_drops_subtexel_features():
    """On a coarse grid, a catalogue of only tiny craters adds nothing."""
    spec = load_spec("A")
    tiny = SiteSpec(**{**spec.__dict__, "craters": type(spec.craters)(**{**spec.craters.__dict__,
                                                                       "d_max_m": 1.0})})
    flat = SiteSpec(**{**spec.__dict__, "craters": type(spec.craters)(**{**spec.craters.__dict__,
                                                                       "density": 0.0})})
    h_tiny, _ = Terrain(tiny).heightmap(640.0, 64)  # 10 m texels, craters <= 1 m
    h_flat, _ = Terrain(flat).heightmap(640.0, 64)
    assert torch.equal(h_tiny, h_flat)


def test_cast_shadow_step():
    """A wall toward the sun shades the ground behind it over height / tan(elevation)."""
    h = torch.zeros(1, 200, dtype=torch.float64)
    h[0, 150:] = 10.0  # a 10 m step; columns grow toward the sun
    lit = cast_shadow(h, 1.0, 45.0)
    assert lit[0, 150:].min() == 1.0
    assert lit[0, 141:150].max() == 0.0  # 10 m / tan 45 = 10 m of shadow
    assert lit[0, :139].min() == 1.0


def test_shade_positive_and_lunar_lambert():
    h = torch.zeros(8, 8, dtype=torch.float64)
    a = torch.full_like(h, 0.1)
    irr, lit = shade(h, a, 1.0, 15.0, 0.02)
    assert (irr > 0).all() and (lit == 1).all()
    lam = lunar_lambert_l(75.0)
    mu0 = math.sin(math.radians(15.0))
    expect = 0.1 * (lam * 2 * mu0 / (mu0 + 1) + (1 - lam) * mu0 + 0.02)
    assert torch.allclose(irr, torch.full_like(irr, expect))


def test_irradiance_has_shadows():
    irr = load_site("A").irradiance(2000.0, 96)
    assert irr.shape == (96, 96) and irr.dtype == torch.float32 and (irr > 0).all()
    flat = float(irr.median())
    assert float((irr < 0.3 * flat).float().mean()) > 0.001  # some cast shadow


def test_extent_errors():
    t = load_site("A")
    with pytest.raises(ValueError, match="extent_m"):
        t.heightmap(-1.0, 16)
    with pytest.raises(ValueError, match="n must"):
        t.heightmap(10.0, 1)


def test_site_variants_are_new_terrain_of_the_same_kind():
    from dvsland.terrain import is_site_name, load_spec, split_site_name
    from dvsland.terrain.spec import VARIANT_SEED_STEP

    a, a1, a2 = load_spec("A"), load_spec("A~1"), load_spec("A~2")
    assert split_site_name("A~2") == ("A", 2) and split_site_name("H") == ("H", 0)
    assert a1.seed == a.seed + VARIANT_SEED_STEP and a2.seed == a.seed + 2 * VARIANT_SEED_STEP
    assert a1.name == "A~1" and a1.craters == a.craters and a1.sun == a.sun
    assert is_site_name("I~7") and not is_site_name("J~1") and not is_site_name("A~0")
    for bad in ("A~", "A~x", "A~-1", "A~0", "Z~1", "A1", 3):
        with pytest.raises(ValueError, match="variant"):
            split_site_name(bad)


def test_site_variant_renders_differently():
    from dvsland.config import CameraConfig, RenderConfig
    from dvsland.render import get_renderer

    cam = CameraConfig(width_px=32, height_px=32, fov_deg=60.0)
    r = get_renderer("fast", ["E", "E~1"], cam, RenderConfig(), disk_cache=False)
    f = r.render(torch.tensor([300.0, 300.0]), torch.tensor([0, 1]))
    assert torch.isfinite(f).all() and (f > 0).all()
    assert not torch.allclose(f[0], f[1])


# ------------------------------------------------------------------ noise and stamps against plain references
def _perlin_plain(x, y, seed):
    """Gradient noise written the plain way (int64 lattice, the permutation table indexed, then the
    gradient table): the reference of :func:`dvsland.terrain.noise.perlin`."""
    import numpy as np

    from dvsland.terrain.noise import _GRAD, _PERIOD, _fade

    p = np.random.default_rng([0x5EED, int(seed) & 0xFFFFFFFF]).permutation(_PERIOD)
    perm = torch.from_numpy(np.concatenate([p, p]).astype(np.int64))
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0).to(torch.float32), (y - y0).to(torch.float32)
    ix, iy = x0.to(torch.int64) & (_PERIOD - 1), y0.to(torch.int64) & (_PERIOD - 1)

    def corner(px, dx, dy):
        k = perm[px + iy + dy] & 15
        return _GRAD[k, 0] * (fx - dx) + _GRAD[k, 1] * (fy - dy)

    u, v = _fade(fx), _fade(fy)
    n0 = torch.lerp(corner(perm[ix], 0, 0), corner(perm[ix + 1], 1, 0), u)
    n1 = torch.lerp(corner(perm[ix], 0, 1), corner(perm[ix + 1], 1, 1), u)
    return torch.lerp(n0, n1, v)


@pytest.mark.parametrize("scale", [3.0, 300.0, 2.0e6])
def test_perlin_equals_plain_reference(scale):
    from dvsland.terrain.noise import perlin

    g = torch.Generator().manual_seed(int(scale))
    x = (torch.rand(64, 48, dtype=torch.float64, generator=g) - 0.5) * scale
    y = (torch.rand(64, 48, dtype=torch.float64, generator=g) - 0.5) * scale
    out = perlin(x, y, 4242)
    assert out.dtype == torch.float32 and out.shape == (64, 48)
    assert torch.equal(out, _perlin_plain(x, y, 4242))


def test_perlin_refuses_points_beyond_int32_lattice():
    from dvsland.terrain.noise import perlin

    far = torch.tensor([3.0e9], dtype=torch.float64)
    with pytest.raises(ValueError, match="2\\^31"):
        perlin(far, far * 0, 1)


def test_stamp_equals_whole_patch_evaluation():
    """Stamps evaluate the profile only inside the reach: the same sums as evaluating whole
    patches and masking (the former way), bit for bit."""
    from dvsland.terrain.features import crater_profile
    from dvsland.terrain.grid import Grid
    from dvsland.terrain.stamp import stamp

    grid = Grid.centered((3.0, -2.0), 40, 50, 0.5, angle_rad=0.3)
    g = torch.Generator().manual_seed(5)
    m = 30
    x, y = (torch.rand(m, dtype=torch.float64, generator=g) - 0.5) * 30, (torch.rand(m, generator=g,
                                                                             dtype=torch.float64) - 0.5) * 30
    d = 0.5 + 6 * torch.rand(m, dtype=torch.float64, generator=g)
    fresh, w = torch.rand(m, dtype=torch.float64, generator=g), torch.rand(m, dtype=torch.float64, generator=g)

    def fn(r, dd, f):
        return crater_profile(r, dd, f, 0.2, 0.04), r * f

    out = [torch.zeros(40 * 50, dtype=torch.float64), torch.zeros(40 * 50, dtype=torch.float64)]
    stamp(out, grid, x, y, d, fresh, w, 2.0, fn)
    ref = [torch.zeros(40 * 50, dtype=torch.float64), torch.zeros(40 * 50, dtype=torch.float64)]
    ci, cj = grid.texel(x, y)
    ii = torch.arange(40, dtype=torch.float64)[:, None]
    jj = torch.arange(50, dtype=torch.float64)[None, :]
    for k in range(m):  # one feature at a time over the whole grid (in the stamps' order of features)
        r = 0.5 * torch.sqrt((ii - ci[k]) ** 2 + (jj - cj[k]) ** 2) / (0.5 * d[k])
        inside = r < 2.0
        for o, v in zip(ref, fn(r[inside], d[k].expand(int(inside.sum())), fresh[k].expand(int(inside.sum())))):
            o.view(40, 50)[inside] += v * w[k]
    for o, r_ in zip(out, ref):
        assert torch.allclose(o, r_, rtol=1e-12, atol=1e-12)
    assert out[0].abs().sum() > 0
