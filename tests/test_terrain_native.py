"""The terrain's compiled noise octaves (dvsland.terrain.native_noise): the same fields and prepared
levels as the torch path, bit for bit; the out-of-range error; the mode switch."""

from __future__ import annotations

import pytest
import torch

from dvsland.terrain import load_site, native_noise, noise

ARGS = dict(seed=7, texel_m=1.0, max_wavelength_m=4000.0, min_wavelength_m=2.0, amplitude_at_1km=30.0, hurst=0.8)


@pytest.fixture(scope="module", autouse=True)
def kernels():
    if native_noise.LIBRARY.load(force=True) is None:
        pytest.skip("no C++ compiler: the compiled noise cannot be built here")


def _fbm(on: bool, *args, **kw) -> torch.Tensor:
    saved = native_noise.LIBRARY.chosen
    native_noise.use_native_noise(on)
    try:
        return noise.fbm(*args, **kw)
    finally:
        native_noise.LIBRARY.chosen = saved


@pytest.mark.parametrize("seed,lam_from,lam_below", [(7, 0.0, float("inf")), (123456, 50.0, 800.0)])
def test_fbm_identical_to_torch_path(seed, lam_from, lam_below, count_calls):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(97, 61, dtype=torch.float64, generator=g) * 6000 - 3000  # negative lattice cells too
    y = torch.rand(97, 61, dtype=torch.float64, generator=g) * 6000 - 1000
    kw = {**ARGS, "seed": seed, "lam_from": lam_from, "lam_below": lam_below}
    calls = count_calls(native_noise.Kernels, "add_octave")
    got = _fbm(True, x, y, **kw)
    want = _fbm(False, x, y, **kw)
    assert calls and got.dtype == torch.float64 and got.shape == (97, 61)
    assert torch.equal(got, want) and float(got.abs().max()) > 0


def test_prepared_levels_identical(monkeypatch):
    from dvsland.render import lod

    monkeypatch.setenv("DVSLAND_CACHE_DIR", "off")
    p = lod.LevelParams(level_size=48, base_texel_m=0.5, n_levels=5)
    out = {}
    for on in (False, True):
        lod._MEMORY.clear()
        native_noise.use_native_noise(on)
        out[on] = [lod.prepare_levels(load_site(s), p, disk_cache=False) for s in ("A", "G")]
    native_noise.use_native_noise(None)
    lod._MEMORY.clear()
    for a, b in zip(out[False], out[True]):
        assert torch.equal(a.irradiance, b.irradiance) and torch.equal(a.height_m, b.height_m)


def test_out_of_range_points_raise_as_on_the_torch_path():
    x = torch.tensor([0.0, 1e13], dtype=torch.float64)
    for on in (True, False):
        with pytest.raises(ValueError, match="within \\+-2\\^31 cells"):
            _fbm(on, x, x.clone(), **{**ARGS, "min_wavelength_m": 2000.0})


def test_mode_off_and_other_inputs_use_torch():
    x = torch.zeros(3, dtype=torch.float64)
    native_noise.use_native_noise(False)
    try:
        assert native_noise.kernel_for(x) is None
    finally:
        native_noise.use_native_noise(None)
    assert noise._octave_kernel(x.float(), x.float(), x) is None  # float32 points: the torch path
    assert noise._octave_kernel(x[::2], x[::2], x[:2]) is None  # strided points
