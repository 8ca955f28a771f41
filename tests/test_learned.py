"""The learned estimator (dvsland.estimators.learned): inputs, models, checkpoints, estimator."""

from __future__ import annotations

import pytest
import torch

from dvsland.estimators import get_estimator
from dvsland.estimators.learned import (InputSpec, SpikingVoxelNet, VoxelCNN, build_model, coord_channels,
                                        load_checkpoint, save_checkpoint, voxel_grid)
from dvsland.events import Events


def _events(B=3, n=400, W=128, H=128, seed=0, t0=0, t1=100_000, skip=()):
    g = torch.Generator().manual_seed(seed)
    b = torch.randint(0, B, (n,), generator=g)
    keep = torch.ones(n, dtype=torch.bool)
    for s in skip:
        keep &= b != s
    b = b[keep]
    m = b.numel()
    t = torch.randint(t0 + 1, t1 + 1, (m,), generator=g)
    order = torch.argsort(b * (t1 + 1) + t)
    return Events(b=b[order], x=torch.randint(0, W, (m,), generator=g)[order],
                  y=torch.randint(0, H, (m,), generator=g)[order], t=t[order],
                  p=(torch.randint(0, 2, (m,), generator=g) * 2 - 1).to(torch.int8)[order])


def _plain(*args, **kwargs):
    """``get_estimator`` with the motion-evidence test off: these tests are about the models and
    their plumbing on arbitrary (uniformly random) events, on which the test makes the estimator
    abstain (tests/test_abstention.py)."""
    est = get_estimator(*args, **kwargs)
    est.abstain = None
    return est


def _checkpoint(path, name="cnn", n_bins=4, pool_px=2, sensor=(128, 128), settings=None):
    net, cls = build_model(name, {"n_bins": n_bins, **(settings or {})})
    spec = InputSpec(sensor, n_bins, pool_px, 64.0)
    save_checkpoint(path, {"model": {"name": name, "class": cls, "settings": net.settings()},
                           "input": {**spec._asdict(), "sensor_size": list(sensor)}, "state_dict": net.state_dict(),
                           "data": {}, "history": []})
    return net


# ------------------------------------------------------------------ inputs
def test_voxel_grid_is_signed_pooled_and_conserves_counts():
    spec = InputSpec((10, 8), n_bins=3, pool_px=2)
    b = torch.tensor([0, 0, 1, 1])
    x = torch.tensor([0, 1, 9, 9])
    y = torch.tensor([0, 0, 7, 7])
    frac = torch.tensor([0.0, 0.25, 1.0, 0.5])
    p = torch.tensor([1, 1, -1, 1], dtype=torch.int8)
    v = voxel_grid(b, x, y, frac, p, 2, spec)
    assert v.shape == (2, 3, 4, 5) and v.dtype == torch.float32
    assert v[0, :, 0, 0].tolist() == pytest.approx([1.5, 0.5, 0.0])  # two ON events in one pooled cell
    assert float(v[1].sum()) == pytest.approx(0.0)  # one OFF and one ON event cancel
    assert v[1, 2, 3, 4] == pytest.approx(-1.0) and v[1, 1, 3, 4] == pytest.approx(1.0)


@pytest.mark.parametrize("pool", [2, 3, 4])
def test_one_bin_grid_compiled_counts_are_the_torch_counts(pool):
    """A ring input's one-bin window (the shipped CNN's) comes from the compiled per-cell counts
    (dvsland.events.native) where a compiler is found: the same grid as the torch path's bincount."""
    from dvsland.events import native

    if native.load() is None:
        pytest.skip("no C++ compiler here")
    spec = InputSpec((45, 30), n_bins=4, pool_px=pool, n_windows=4)
    g = torch.Generator().manual_seed(pool)
    n = 5000
    b = torch.sort(torch.randint(0, 3, (n,), generator=g)).values
    x, y = torch.randint(0, 45, (n,), generator=g), torch.randint(0, 30, (n,), generator=g)
    p = (torch.randint(0, 2, (n,), generator=g) * 2 - 1).to(torch.int8)
    got = voxel_grid(b, x, y, b, p, 3, spec, spec.bins_per_window)
    with native.native_sort_mode(False):
        want = voxel_grid(b, x, y, b, p, 3, spec, spec.bins_per_window)
    assert got.shape == want.shape == (3, 1, *spec.grid_hw) and got.dtype == want.dtype == torch.float32
    assert torch.equal(got, want) and float(got.abs().sum()) > 0


@pytest.mark.parametrize("field,value", [("b", 3), ("b", -1), ("x", 44), ("y", 30)])
def test_one_bin_compiled_counts_refuse_an_event_off_the_grid(field, value):
    """An event outside the B x h x w grid, even after others were counted, makes the compiled counts
    return None (the caller then runs the torch path): no partial grid comes back."""
    from dvsland.events import native

    mod = native.kernels()
    if mod is None:
        pytest.skip("no C++ compiler here")
    n = 200
    ev = {"b": torch.zeros(n, dtype=torch.int64), "x": torch.full((n,), 3), "y": torch.full((n,), 4)}
    p = torch.ones(n, dtype=torch.int8)
    assert float(mod.cell_counts(ev["b"], ev["x"], ev["y"], p, 3, 15, 22, 2).sum()) == n  # 44 x 30 px
    ev[field][n // 2] = value
    assert mod.cell_counts(ev["b"], ev["x"], ev["y"], p, 3, 15, 22, 2) is None


def test_coord_channels_are_relative_to_the_principal_point():
    spec = InputSpec((128, 128), pool_px=1, coord_scale_px=64.0)
    c = coord_channels(spec, (10.0, 20.0))
    assert c.shape == (1, 2, 128, 128)
    assert float(c[0, 0, 0, 10]) == 0.0 and float(c[0, 1, 20, 0]) == 0.0
    assert float(c[0, 0, 0, 74]) == pytest.approx(1.0)


# ------------------------------------------------------------------ models
@pytest.mark.parametrize("cls,nb", [(VoxelCNN, 4), (SpikingVoxelNet, 6)])
def test_models_give_mu_and_log_var_per_row(cls, nb):
    net = cls(n_bins=nb) if cls is VoxelCNN else cls(n_bins=nb, slice_dt_s=0.1 / nb)
    spec = InputSpec((64, 48), nb, 2)
    vox = torch.randn(5, nb, *spec.grid_hw)
    mu, lv = net(vox, coord_channels(spec, (31.5, 23.5)), torch.ones(5))
    assert mu.shape == (5,) and lv.shape == (5,) and torch.isfinite(mu).all() and torch.isfinite(lv).all()
    (mu.sum() + lv.sum()).backward()
    assert all(p.grad is not None for p in net.parameters())
    if cls is SpikingVoxelNet:
        assert set(net.last_activity) == {"spikes", "synops"} and net.last_activity["spikes"].shape == (5,)


def test_bad_model_settings_name_the_parameter():
    with pytest.raises(ValueError, match="width"):
        VoxelCNN(width=0)
    with pytest.raises(ValueError, match="dt_s"):
        SpikingVoxelNet(n_bins=4, slice_dt_s=1.0)
    with pytest.raises(ValueError, match="unknown model"):
        build_model("nope", {})


def test_spiking_depth_and_hidden_options():
    base = SpikingVoxelNet(n_bins=4, width=4, slice_dt_s=0.02)
    assert "depth" not in base.settings() and "hidden" not in base.settings()  # shipped checkpoints: unchanged
    torch.manual_seed(0)
    net = SpikingVoxelNet(n_bins=4, width=4, slice_dt_s=0.02, depth=3, hidden=8)
    assert net.settings()["depth"] == 3 and net.settings()["hidden"] == 8
    rebuilt, _ = build_model("spiking", net.settings())
    rebuilt.load_state_dict(net.state_dict())  # the settings rebuild the same tensors
    with torch.no_grad():
        for conv in (net.conv1, net.conv2, net.conv3):
            conv.weight.mul_(6.0)  # enough drive that every layer spikes
    spec = InputSpec((64, 64), 4, 2)
    vox = torch.randn(3, 4, *spec.grid_hw) * 3
    mu, lv = net(vox, coord_channels(spec, (31.5, 31.5)), torch.ones(3))
    assert mu.shape == (3,) and torch.isfinite(mu).all() and torch.isfinite(lv).all()
    act = net.last_activity
    assert (act["spikes"] > 0).all() and (act["synops"] > act["spikes"]).all()
    with pytest.raises(ValueError, match="depth must be 2 or 3"):
        SpikingVoxelNet(depth=4)
    with pytest.raises(ValueError, match=r"hidden must be in \[0, 1024\]"):
        SpikingVoxelNet(hidden=-1)


@pytest.mark.parametrize("settings", [{"depth": 3, "hidden": 8}, {"delay": 1, "per_step": True}],
                         ids=["depth3", "delay_per_step"])
def test_spiking_variants_nir_round_trip_agrees(tmp_path, settings):
    pytest.importorskip("nir")
    pytest.importorskip("nirtorch")
    from dvsland.estimators.learned.nir_export import export_nir, from_nir, run_nir

    torch.manual_seed(2)
    net = SpikingVoxelNet(n_bins=4, width=4, slice_dt_s=0.02, **settings).eval()
    with torch.no_grad():
        for conv in (net.conv1, *net._layers()):
            conv.weight.mul_(6.0)
    spec = InputSpec((64, 64), 4, 2)
    coords = coord_channels(spec, (31.5, 31.5))
    vox, lc = torch.randn(2, 4, *spec.grid_hw) * 3, torch.full((2,), 5.0)
    with torch.no_grad():
        want = net(vox, coords, lc)
    got = run_nir(from_nir(export_nir(net, spec.grid_hw, tmp_path / "s.nir")), net, vox, coords, lc)
    assert torch.allclose(got[0], want[0], atol=1e-5) and torch.allclose(got[1], want[1], atol=1e-5)


def test_spiking_delay_feeds_the_previous_bin_and_per_step_reads_each_step():
    base = SpikingVoxelNet(n_bins=4, width=4, slice_dt_s=0.02)
    assert "delay" not in base.settings() and "per_step" not in base.settings()  # shipped: unchanged
    torch.manual_seed(1)
    net = SpikingVoxelNet(n_bins=4, width=4, slice_dt_s=0.02, delay=1, per_step=True)
    assert net.settings()["delay"] == 1 and net.settings()["per_step"] is True
    assert net.conv1.in_channels == 4 and net.head.in_features == 4 * 4 * 4 + 1
    rebuilt, _ = build_model("spiking", net.settings())
    rebuilt.load_state_dict(net.state_dict())
    spec = InputSpec((64, 64), 4, 2)
    coords = coord_channels(spec, (31.5, 31.5))
    vox = torch.randn(3, 4, *spec.grid_hw) * 3
    x = net.slice_inputs(vox, coords)  # (B, T, [bin k, bin k - 1, x, y], h, w)
    assert x.shape == (3, 4, 4, *spec.grid_hw)
    assert torch.equal(x[:, 1:, 1], x[:, :-1, 0]) and (x[:, 0, 1] == 0).all()
    assert torch.equal(x[:, :, 2:], coords.expand(3, 4, -1, -1, -1))
    with torch.no_grad():
        net.conv1.weight.mul_(6.0)
        net.conv2.weight.mul_(6.0)
        mu, lv = net(vox, coords, torch.ones(3))
        # the per-step head reads when the spikes came: the window's steps reversed read differently
        # while the summed count (and so the sum read-out) cannot tell
        mu_rev, _ = net(vox.flip(1), coords, torch.ones(3))
    assert mu.shape == (3,) and torch.isfinite(mu).all() and torch.isfinite(lv).all()
    assert (net.last_activity["spikes"] > 0).all()
    assert not torch.allclose(mu, mu_rev)
    with pytest.raises(ValueError, match=r"delay must be in \[0, n_bins - 1 = 3\]"):
        SpikingVoxelNet(n_bins=4, delay=4)


# ------------------------------------------------------------------ estimator
@pytest.fixture
def ckpt(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "m.pt"
    _checkpoint(path)
    return path


def test_estimator_shapes_nan_without_events_and_confidence(ckpt):
    est = _plain("learned", 3, (128, 128), checkpoint=str(ckpt), min_events=5)
    d = est.update(_events(3, 600, skip=(1,)), 100_000)
    assert d.shape == (3,) and d.dtype == torch.float32
    assert torch.isnan(d[1]) and torch.isfinite(d[[0, 2]]).all() and (d[[0, 2]] < 0).all()
    c = est.confidence()
    assert c.shape == (3,) and c[1] == 0 and ((c >= 0) & (c <= 1)).all()
    diag = est.diagnostics()
    assert diag["n_events"][1] == 0 and torch.isnan(diag["sigma_rel"][1])


def test_estimator_reset_by_mask_clears_only_those_rows(ckpt):
    est = _plain("learned", 3, (128, 128), checkpoint=str(ckpt), min_events=1)
    d = est.update(_events(3, 600), 100_000)
    assert torch.isfinite(d).all()
    est.reset(torch.tensor([False, True, False]))
    assert torch.isnan(est.state.d[1]) and torch.equal(est.state.d[[0, 2]], d[[0, 2]])
    assert est.confidence()[1] == 0
    with pytest.raises(ValueError, match="mask"):
        est.reset(torch.tensor([True]))


def test_estimator_rows_are_independent(ckpt):
    """A row's estimate depends on its own events only (no mixing across the batch)."""
    ev = _events(3, 900)
    full = _plain("learned", 3, (128, 128), checkpoint=str(ckpt), min_events=1).update(ev, 100_000)
    keep = ev.b == 2
    one = Events(b=ev.b[keep] * 0, x=ev.x[keep], y=ev.y[keep], t=ev.t[keep], p=ev.p[keep])
    single = _plain("learned", 1, (128, 128), checkpoint=str(ckpt), min_events=1).update(one, 100_000)
    assert float(single[0]) == pytest.approx(float(full[2]), rel=1e-5)


def test_corrupted_checkpoint_is_a_clear_error(tmp_path, ckpt):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(ckpt.read_bytes()[:300])
    with pytest.raises(ValueError, match="estimator.learned.checkpoint.*not a readable"):
        _plain("learned", 2, (128, 128), checkpoint=str(bad))
    with pytest.raises(ValueError, match="estimator.learned.checkpoint: file not found"):
        _plain("learned", 2, (128, 128), checkpoint=str(tmp_path / "none.pt"))
    other = tmp_path / "other.pt"
    torch.save({"state_dict": {}}, other)
    with pytest.raises(ValueError, match="estimator.learned.checkpoint.*not a dvsland learned checkpoint"):
        _plain("learned", 2, (128, 128), checkpoint=str(other))


def test_mismatched_checkpoint_names_tensor_and_sensor(tmp_path, ckpt):
    ck = torch.load(ckpt, weights_only=True)
    ck["input"]["n_bins"] = 5  # weights of a 4-bin network described as 5 bins
    ck["model"]["settings"]["n_bins"] = 5
    torch.save(ck, tmp_path / "mis.pt")
    with pytest.raises(ValueError, match="estimator.learned.checkpoint.*tensor 'features.0.weight'"):
        _plain("learned", 2, (128, 128), checkpoint=str(tmp_path / "mis.pt"))
    ck = torch.load(ckpt, weights_only=True)
    ck["state_dict"]["head.2.bias"][0] = float("nan")
    torch.save(ck, tmp_path / "nan.pt")
    with pytest.raises(ValueError, match="NaN"):
        _plain("learned", 2, (128, 128), checkpoint=str(tmp_path / "nan.pt"))
    with pytest.raises(ValueError, match="128 x 128 sensor"):
        load_checkpoint(ckpt, sensor_size=(346, 260))
    with pytest.raises(ValueError, match="min_events"):
        _plain("learned", 2, (128, 128), checkpoint=str(ckpt), min_events=0)


def test_spiking_checkpoint_runs_in_the_estimator_and_reports_activity(tmp_path):
    _checkpoint(tmp_path / "s.pt", "spiking", n_bins=6, pool_px=4, settings={"slice_dt_s": 0.1 / 6})
    est = _plain("learned", 2, (128, 128), checkpoint=str(tmp_path / "s.pt"), min_events=1)
    d = est.update(_events(2, 500), 100_000)
    assert d.shape == (2,)
    diag = est.diagnostics()
    assert diag["spikes"].shape == (2,) and diag["synops"].shape == (2,) and (diag["synops"] >= 0).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_and_cuda_agree(ckpt):
    ev = _events(3, 900)
    cpu = _plain("learned", 3, (128, 128), checkpoint=str(ckpt), min_events=1).update(ev, 100_000)
    gpu = _plain("learned", 3, (128, 128), "cuda", checkpoint=str(ckpt), min_events=1)
    evg = Events(**{k: getattr(ev, k).cuda() for k in "bxytp"})
    assert torch.allclose(gpu.update(evg, 100_000).cpu(), cpu, rtol=1e-4)


def test_spiking_nir_round_trip_agrees(tmp_path):
    pytest.importorskip("nir")
    pytest.importorskip("nirtorch")
    from dvsland.estimators.learned.nir_export import export_nir, from_nir, run_nir

    torch.manual_seed(1)
    net = SpikingVoxelNet(n_bins=6, width=6, slice_dt_s=0.1 / 6).eval()
    with torch.no_grad():  # enough drive that both layers spike
        net.conv1.weight.mul_(4.0)
        net.conv2.weight.mul_(4.0)
    spec = InputSpec((128, 128), 6, 4)
    coords = coord_channels(spec, (63.5, 63.5))
    vox = torch.randn(3, 6, *spec.grid_hw) * 3
    lc = torch.full((3,), 5.0)
    with torch.no_grad():
        want = net(vox, coords, lc)
    assert float(net.last_activity["spikes"].min()) > 0
    module = from_nir(export_nir(net, spec.grid_hw, tmp_path / "s.nir"))
    got = run_nir(module, net, vox, coords, lc)
    assert torch.allclose(got[0], want[0], atol=1e-5) and torch.allclose(got[1], want[1], atol=1e-5)


@pytest.mark.parametrize("which", ["", "spiking", "spiking8", "spiking8_both", "spiking8_dagger", "spiking8_px2",
                                   "spiking8_px2_more", "cnn_realistic", "cnn_landing", "cnn_wide", "cnn_dagger",
                                   "cnn_both"])
def test_shipped_checkpoints_load_and_estimate(which):
    from dvsland.estimators.learned.estimator import SHIPPED

    path = SHIPPED["cnn" if which == "" else which]
    assert path.is_file() and path.stat().st_size < 1_000_000
    est = _plain("learned", 2, (128, 128), checkpoint=which, min_events=1)
    assert est.meta["data"]["config_hash"] and est.meta["train"]["model"] == ("spiking" if "spiking" in which else "cnn")
    d = est.update(_events(2, 3000), 100_000)
    assert d.shape == (2,) and torch.isfinite(d).all() and (d < 0).all()


# ------------------------------------------------------------------ speed paths and other cameras
def test_ring_path_agrees_with_the_model(ckpt, tmp_path):
    """The circular ring with the folded first layer (fast="ring", the default) gives the model's
    numbers to float32 rounding, across updates and a reset by mask; bfloat16 within 2 %."""
    _checkpoint(tmp_path / "k4.pt", n_bins=4).eval()
    ck = torch.load(tmp_path / "k4.pt", weights_only=True)
    ck["input"]["n_windows"] = 4
    torch.save(ck, tmp_path / "k4.pt")
    outs = {}
    for fast in ("", "ring", "bf16"):
        est = _plain("learned", 3, (128, 128), checkpoint=str(tmp_path / "k4.pt"), min_events=1, fast=fast)
        rows = []
        for k in range(1, 8):
            rows.append(est.update(_events(3, 700, seed=k, t0=(k - 1) * 100_000, t1=k * 100_000), k * 100_000))
            if k == 3:
                est.reset(torch.tensor([False, True, False]))
        outs[fast] = torch.stack(rows)
    ref = outs[""]
    assert torch.isfinite(ref).all()
    assert torch.allclose(outs["ring"], ref, rtol=1e-5, atol=0)
    assert ((outs["bf16"] - ref).abs() / ref.abs()).max() < 0.02
    with pytest.raises(ValueError, match="estimator.learned.fast"):
        _plain("learned", 3, (128, 128), checkpoint=str(tmp_path / "k4.pt"), fast="nope")


def test_other_camera_events_land_on_the_reference_canvas():
    """A camera of finer pixels and an off-centre principal point: the principal point maps to the
    canvas centre, pixels scale by f_ref / f, events off the canvas are dropped; the reference
    camera itself is the identity."""
    from dvsland.estimators.learned.inputs import camera_map, to_reference

    spec = InputSpec((128, 128), 8, 2, 64.0, 8)
    assert camera_map(spec, (128, 128), None, spec.reference_focal_px).identity
    cm = camera_map(spec, (346, 260), (140.5, 150.5), 297.3)
    assert not cm.identity and cm.scale == pytest.approx(110.85 / 297.3, rel=1e-3)
    x = torch.tensor([140, 141, 0, 345, 140])
    y = torch.tensor([150, 151, 150, 150, 0])
    xi, yi, keep = to_reference(x, y, cm, spec)
    assert xi[:2].tolist() == [63, 64] and yi[:2].tolist() == [63, 64]  # either side of the centre 63.5
    assert keep.tolist() == [True, True, True, False, True]  # 204.5 px right of it: 76 reference px, off
    assert int(xi[2]) == int(63.5 - 140.5 * cm.scale + 0.5) and int(yi[4]) == int(63.5 - 150.5 * cm.scale + 0.5)


def _offcentre_zoom_events(d: float, B: int, steps: int, cam):
    """Events of a random texture zoomed at divergence d (1/s) on ``cam``, recorded as the dataset
    build records an off-centre principal point (a larger centred sensor, cropped)."""
    from dvsland.data.crop import recording_camera
    from dvsland.evaluate import ZoomTextureFrames
    from dvsland.events import EventEmulator

    big, crop = recording_camera(cam)
    src = ZoomTextureFrames(B, (big.width_px, big.height_px), big.fov_deg, seed=3)
    idx = torch.arange(B)
    frames = [src(torch.full((B,), 800.0 * float(torch.exp(torch.tensor(d * 0.1 * k)))), idx) for k in range(steps + 1)]
    emu = EventEmulator()
    emu.reset(frames[0], 0)
    out = []
    for k, f in enumerate(frames[1:], start=1):
        ev = emu.step(f, 100_000 * k)
        x, y = ev.x - crop.x0, ev.y - crop.y0
        keep = (x >= 0) & (x < crop.width) & (y >= 0) & (y < crop.height)
        out.append(Events(b=ev.b[keep], x=x[keep], y=y[keep], t=ev.t[keep], p=ev.p[keep]))
    return out


def test_davis346_offcentre_zoom_gives_the_divergence():
    """The shipped CNN (trained on a centred DVS128) on a DAVIS346 whose principal point is 32 px
    left of and 21 px below the centre: a synthetic zoom at D = -0.2 1/s reads finite, negative
    estimates of the right size once its 8-step ring is full."""
    from dvsland.config import CameraConfig

    cam = CameraConfig(sensor="davis346", principal_point_px=[140.5, 150.5])
    events = _offcentre_zoom_events(-0.2, 2, 10, cam)
    est = _plain("learned", 2, (346, 260), principal_point_px=[140.5, 150.5])
    assert est.focal_px == pytest.approx(5.5 / 18.5e-3) and not est.cmap.identity
    d = [est.update(ev, 100_000 * k) for k, ev in enumerate(events, start=1)]
    late = torch.stack(d[8:])
    assert torch.isfinite(late).all() and (late < 0).all()
    assert ((late + 0.2).abs() / 0.2).median() < 0.35


def test_pixel_table_grid_equals_the_mapped_grid():
    """The look-up path of another camera builds the same grid and canvas counts as the float mapping."""
    from dvsland.estimators.learned.inputs import camera_map, events_voxel_grid, pixel_cells

    for nw in (8, 4):
        spec = InputSpec((128, 128), 8, 2, 64.0, nw)
        cm = camera_map(spec, (346, 260), (140.5, 150.5), 297.3)
        ev = _events(3, 5000, W=346, H=260, seed=4)
        a = events_voxel_grid(ev, 0, 100_000, 3, spec, cm)
        b = events_voxel_grid(ev, 0, 100_000, 3, spec, cm, pixel_cells(cm, spec, (346, 260)))
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]) and a[0].abs().sum() > 0
