"""Events container, representations (count image, voxel grid), tonic interop, file I/O."""

import numpy as np
import pytest
import torch

from dvsland.events import TONIC_DTYPE, EventEmulator, Events
from dvsland.events.io import load_events, save_events


def random_events(n=500, B=3, H=6, W=7, seed=0, t_max=10_000):
    g = torch.Generator().manual_seed(seed)
    return Events(b=torch.randint(0, B, (n,), generator=g), x=torch.randint(0, W, (n,), generator=g),
                  y=torch.randint(0, H, (n,), generator=g), t=torch.randint(0, t_max, (n,), generator=g),
                  p=torch.randint(0, 2, (n,), generator=g) * 2 - 1, sort=True)


# ----------------------------------------------------------------------------- container
def test_container_basics():
    ev = random_events()
    assert len(ev) == 500 and ev.is_sorted()
    assert ev.b.dtype == ev.x.dtype == ev.y.dtype == ev.t.dtype == torch.int64
    assert ev.p.dtype == torch.int8
    on = ev[ev.p > 0]
    assert len(on) == int((ev.p > 0).sum()) and bool((on.p == 1).all())
    e0 = ev.select_batch(0)
    assert bool((e0.b == 0).all())
    assert len(Events.empty()) == 0 and Events.empty().device == torch.device("cpu")
    assert ev.to("cpu") == ev
    assert int(ev.batch_counts(3).sum()) == 500
    w = ev.time_window(1000, 2000)
    assert bool(((w.t >= 1000) & (w.t < 2000)).all())


def test_cat_resorts_and_keeps_ties_stable():
    a, b = random_events(seed=1), random_events(seed=2)
    c = Events.cat([b, a])
    assert len(c) == len(a) + len(b) and c.is_sorted()
    both = sorted(zip(*(getattr(a, k).tolist() + getattr(b, k).tolist() for k in "bxytp")))
    assert sorted(zip(*(getattr(c, k).tolist() for k in "bxytp"))) == both
    # ties in (b, t) keep list order
    one = Events(b=[0], x=[1], y=[1], t=[5], p=[1])
    two = Events(b=[0], x=[2], y=[2], t=[5], p=[-1])
    assert Events.cat([one, two]).x.tolist() == [1, 2]
    assert Events.cat([two, one]).x.tolist() == [2, 1]
    assert len(Events.cat([])) == 0


def test_container_errors():
    with pytest.raises(ValueError, match="equal length"):
        Events(b=[0, 0], x=[1], y=[1], t=[1], p=[1])
    with pytest.raises(ValueError, match="1-D"):
        Events(b=[[0]], x=[[1]], y=[[1]], t=[[1]], p=[[1]])
    with pytest.raises(ValueError, match="integer"):
        Events(b=[0], x=[1.5], y=[1], t=[1], p=[1])
    ev = random_events()
    with pytest.raises(ValueError, match="mask"):
        ev[torch.ones(3, dtype=torch.bool)]
    with pytest.raises(ValueError, match="'x'"):
        ev.validate(3, 6, 5)
    with pytest.raises(ValueError, match="polarity"):
        Events(b=[0], x=[1], y=[1], t=[1], p=[0]).validate()
    with pytest.raises(ValueError, match="sorted"):
        Events(b=[0, 0], x=[1, 1], y=[1, 1], t=[5, 1], p=[1, 1]).validate()


# ----------------------------------------------------------------------------- count image
def test_count_image_conservation_and_reference():
    ev = random_events(n=2000)
    img = ev.to_count_image(3, 6, 7)
    assert img.shape == (3, 2, 6, 7) and img.dtype == torch.float32
    assert int(img.sum()) == len(ev)
    assert int(img[:, 0].sum()) == int((ev.p > 0).sum())  # channel 0 = ON
    ref = np.zeros((3, 2, 6, 7), np.float32)
    for b, x, y, p in zip(ev.b.tolist(), ev.x.tolist(), ev.y.tolist(), ev.p.tolist()):
        ref[b, 0 if p > 0 else 1, y, x] += 1
    assert np.array_equal(img.numpy(), ref)


def test_count_image_of_emulator_output():
    f0 = torch.rand(2, 9, 11, generator=torch.Generator().manual_seed(0)) + 0.05
    f1 = f0 * torch.exp(2 * torch.randn(2, 9, 11, generator=torch.Generator().manual_seed(1)))
    emu = EventEmulator()
    emu.reset(f0, 0)
    ev = emu.step(f1, 100_000)
    img = ev.to_count_image(2, 9, 11)
    assert int(img.sum()) == len(ev) > 0
    assert not bool(((img[:, 0] > 0) & (img[:, 1] > 0)).any())  # one polarity per pixel per step


def test_count_image_errors():
    ev = random_events()
    with pytest.raises(ValueError, match="'b'"):
        ev.to_count_image(2, 6, 7)
    with pytest.raises(ValueError, match="height"):
        ev.to_count_image(3, 0, 7)


# ----------------------------------------------------------------------------- voxel grid
def voxel_reference(ev, n_bins, t0, t1, B, H, W):
    grid = np.zeros((B, n_bins, H, W), np.float64)
    for b, x, y, t, p in zip(*(getattr(ev, k).tolist() for k in "bxytp")):
        if not (t0 <= t <= t1):
            continue
        u = (n_bins - 1) * (t - t0) / (t1 - t0)
        for k in range(n_bins):
            w = max(0.0, 1.0 - abs(u - k))
            grid[b, k, y, x] += p * w
    return grid


@pytest.mark.parametrize("n_bins", [1, 2, 5])
def test_voxel_grid_against_reference(n_bins):
    ev = random_events(n=1500, t_max=12_000)
    grid = ev.to_voxel_grid(n_bins, 1000, 11_000, 3, 6, 7)
    assert grid.shape == (3, n_bins, 6, 7) and grid.dtype == torch.float32
    ref = voxel_reference(ev, n_bins, 1000, 11_000, 3, 6, 7)
    assert np.allclose(grid.numpy(), ref, atol=1e-4)


def test_voxel_grid_polarity_signed_and_sum():
    """OFF events stay negative (tonic's bool-polarity bug), and each event's weights sum to p."""
    ev = Events(b=[0, 0], x=[0, 1], y=[0, 0], t=[0, 100], p=[-1, 1])
    grid = ev.to_voxel_grid(3, 0, 100, 1, 1, 2)
    assert grid[0, 0, 0, 0] == -1 and grid[0, 2, 0, 1] == 1
    ev = random_events(n=800)
    grid = ev.to_voxel_grid(4, 0, 10_000, 3, 6, 7)
    assert torch.allclose(grid.sum(), ev.p.sum().float(), atol=1e-3)
    with pytest.raises(ValueError, match="t1_us"):
        ev.to_voxel_grid(4, 10, 10, 3, 6, 7)
    with pytest.raises(ValueError, match="n_bins"):
        ev.to_voxel_grid(0, 0, 10, 3, 6, 7)


# ----------------------------------------------------------------------------- tonic
def test_tonic_round_trip():
    ev = random_events(n=300)
    arr, sensor_size = ev.to_tonic(1, height=6, width=7)
    assert arr.dtype == TONIC_DTYPE and sensor_size == (7, 6, 2)
    assert set(np.unique(arr["p"]).tolist()) <= {0, 1}
    e1 = ev.select_batch(1)
    assert np.array_equal(arr["p"], (e1.p.numpy() > 0).astype(np.int8))
    back = Events.from_tonic(arr, b=1)
    assert back == e1  # OFF = 0 maps back to -1
    # tonic arrays with bool polarity and other integer widths also load
    arr2 = np.zeros(3, dtype=[("x", np.int64), ("y", np.int64), ("t", np.int64), ("p", bool)])
    arr2["t"] = [3, 1, 2]
    arr2["p"] = [True, False, True]
    e2 = Events.from_tonic(arr2)
    assert e2.t.tolist() == [1, 2, 3] and e2.p.tolist() == [-1, 1, 1]
    with pytest.raises(ValueError, match="fields"):
        Events.from_tonic(np.zeros(2, dtype=[("x", int), ("t", int)]))


# ----------------------------------------------------------------------------- file I/O
@pytest.mark.parametrize("suffix", [".npz", ".h5"])
def test_file_round_trip(tmp_path, suffix):
    ev = random_events(n=1000)
    ev = Events(b=ev.b, x=ev.x, y=ev.y, t=ev.t + 10 ** 10, p=ev.p)  # large times stay exact
    path = save_events(tmp_path / f"ev{suffix}", ev, sensor_size=(7, 6), batch_size=3,
                       threshold=0.1, threshold_off=0.2, refractory_us=15.0)
    assert path.name == f"ev{suffix}"
    back, meta = load_events(path, with_meta=True)
    assert back == ev
    assert meta["sensor_size"] == (7, 6, 2) and meta["batch_size"] == 3
    assert meta["threshold"] == 0.1 and meta["threshold_off"] == 0.2 and meta["refractory_us"] == 15.0
    empty = save_events(tmp_path / f"empty{suffix}", Events.empty())
    assert len(load_events(empty)) == 0


def test_h5_layout(tmp_path):
    import h5py

    path = save_events(tmp_path / "ev.h5", random_events(), sensor_size=(7, 6), threshold=0.1)
    with h5py.File(path, "r") as h5:
        g = h5["events"]
        assert {k: g[k].dtype for k in "bxytp"} == {
            "b": np.int64, "x": np.int16, "y": np.int16, "t": np.int64, "p": np.int8}
        assert list(g.attrs["sensor_size"]) == [7, 6, 2] and g.attrs["threshold"] == 0.1


def test_file_errors(tmp_path):
    with pytest.raises(ValueError, match="format"):
        save_events(tmp_path / "ev.txt", random_events())
    with pytest.raises(FileNotFoundError):
        load_events(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="not a dvsland events file"):
        load_events(tmp_path / "other.npz")


# ------------------------------------------------------------------ count-image order, unpacking
def test_count_image_polarity_order_tonic():
    ev = Events(b=[0, 0, 0, 1], x=[0, 1, 1, 2], y=[0, 0, 0, 1], t=[1, 2, 3, 4], p=[1, -1, -1, 1])
    ours = ev.to_count_image(2, 2, 3)
    tonic = ev.to_count_image(2, 2, 3, polarity_order="tonic")
    assert ours[0, 0, 0, 0] == 1 and ours[0, 1, 0, 1] == 2  # channel 0 = ON
    assert torch.equal(tonic, ours.flip(1))                  # tonic: channel 0 = OFF, 1 = ON
    assert torch.equal(ev.to_count_image(2, 2, 3, polarity_order="dvsland"), ours)
    with pytest.raises(ValueError, match="polarity_order"):
        ev.to_count_image(2, 2, 3, polarity_order="on_first")


def test_count_image_tonic_order_matches_tonic_arrays():
    """Channel c of the tonic order holds the events whose tonic polarity index p01 is c."""
    ev = Events(b=[0] * 5, x=[0, 1, 2, 2, 0], y=[0, 0, 1, 1, 1], t=[1, 2, 3, 4, 5], p=[1, -1, 1, 1, -1])
    arr, _ = ev.to_tonic(0, height=2, width=3)
    img = ev.to_count_image(1, 2, 3, polarity_order="tonic")[0]
    ref = np.zeros((2, 2, 3), np.float32)
    np.add.at(ref, (arr["p"].astype(int), arr["y"].astype(int), arr["x"].astype(int)), 1)
    assert np.array_equal(img.numpy(), ref)


def test_unpacking_events_says_what_happened(tmp_path):
    from dvsland.events import load_events, save_events

    ev = Events(b=[0, 0], x=[0, 1], y=[0, 0], t=[1, 2], p=[1, -1])
    path = save_events(tmp_path / "e.npz", ev, sensor_size=(2, 1))
    with pytest.raises(TypeError, match=r"with_meta=True") as exc:
        events, meta = load_events(path)  # noqa: F841
    assert "must be 1-D" not in str(exc.value)
    events, meta = load_events(path, with_meta=True)  # the fix the message names
    assert events == ev and meta["sensor_size"] == (2, 1, 2)
    with pytest.raises(TypeError, match="not iterable"):
        list(ev)
    with pytest.raises(TypeError, match=r"events\[1:2\]"):
        ev[1]
    with pytest.raises(TypeError, match="slice"):
        ev[torch.tensor(0)]
    assert len(ev[1:2]) == 1 and len(ev[torch.tensor([0, 1])]) == 2


@pytest.mark.parametrize("share", [0.0, 0.5, 1.0])
def test_mask_selection_keeps_each_field_and_the_order(share):
    """``ev[mask]`` finds the kept positions once and takes every field at them: the same events, in
    the same order, as masking each field (none kept, some, all)."""
    ev = random_events()
    mask = torch.rand(len(ev), generator=torch.Generator().manual_seed(1)) < share
    sub = ev[mask]
    assert len(sub) == int(mask.sum())
    for k in ("b", "x", "y", "t", "p"):
        assert torch.equal(getattr(sub, k), getattr(ev, k)[mask]) and getattr(sub, k).dtype == getattr(ev, k).dtype
