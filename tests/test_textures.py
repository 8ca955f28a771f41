"""Renderer ``textures``: procedural scale-free ground (smoke, exceptions, shapes, the zoom
property against a box-filtered reference, determinism)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from dvsland.config import CameraConfig
from dvsland.render import TextureRenderer, available_renderers, get_renderer

pytestmark = pytest.mark.usefixtures("one_thread")


def _r(names=("A", "B~2"), **kw):
    return TextureRenderer(list(names), CameraConfig(), **kw)


def test_smoke_shape_dtype_and_registry():
    assert "textures" in available_renderers()
    r = get_renderer("textures", ["A", "C"])
    f = r.render(torch.tensor([3000.0, 40.0]), torch.tensor([0, 1]))
    assert f.shape == (2, 128, 128) and f.dtype == torch.float32
    assert torch.isfinite(f).all() and float(f.min()) >= 0.0199  # the floor (float32)
    assert float(f.std()) > 0.02  # a texture, not a flat field
    assert r.render(torch.zeros(0), torch.zeros(0, dtype=torch.int64)).shape == (0, 128, 128)


def test_deterministic_per_name_and_seed():
    z = torch.tensor([500.0, 500.0])
    a = _r().render(z, torch.tensor([0, 1]))
    assert torch.equal(a, _r().render(z, torch.tensor([0, 1])))
    b = _r(names=("B~2", "A")).render(z, torch.tensor([1, 0]))  # the texture follows the name, not the slot
    assert torch.equal(a, b)
    assert not torch.equal(a[0], a[1])
    assert not torch.equal(a, _r(seed=1).render(z, torch.tensor([0, 1])))


@pytest.mark.parametrize("bad, match", [({"n_waves": 0}, "n_waves"), ({"n_shapes": 5000}, "n_shapes"),
                                        ({"altitude_range_m": (100.0, 50.0)}, "altitude_range_m")])
def test_bad_arguments_name_the_parameter(bad, match):
    with pytest.raises(ValueError, match=match):
        _r(**bad)


def test_bad_inputs_are_refused():
    r = _r()
    with pytest.raises(ValueError, match="altitude_m"):
        r.render(torch.tensor([1.0, 100.0]), torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="site_idx"):
        r.render(torch.tensor([100.0]), torch.tensor([2]))


@pytest.mark.parametrize("z", [60.0, 900.0, 7000.0])
def test_doubling_the_altitude_halves_the_scene_about_the_centre(z):
    """A pixel at 2z covers the 2 x 2 pixels at z about the centre: the central half of the frame at 2z
    matches the frame at z box-filtered by 2 (the renderer integrates each wave over the pixel, so
    only the waves faded at the Nyquist limit and the ellipses' ramps differ)."""
    r = _r(names=("D",))
    near, far = r.render(torch.tensor([z, 2 * z]), torch.tensor([0, 0]))
    ref = F.avg_pool2d(near[None, None], 2)[0, 0]  # (64, 64): the whole frame at z, pixels of 2z
    crop = far[32:96, 32:96]
    a, b = ref - ref.mean(), crop - crop.mean()
    corr = float((a * b).sum() / (a.norm() * b.norm()))
    assert corr > 0.9, corr
    assert float((ref - crop).abs().mean()) < 0.25 * float(ref.std()) + 0.02
