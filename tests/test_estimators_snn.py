"""The spiking estimator 'snn': LIF primitives, log-polar encoding, the network, the estimator
with the shipped checkpoint, and a training smoke test."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dvsland.events import Events
from dvsland.estimators import available_estimators, get_estimator
from dvsland.estimators.snn import (DEFAULT_CHECKPOINT, LIFParameters, LogPolarEncoder, SpikingDivergenceNet,
                                    lif_step, spike)
from dvsland.estimators.snn.lif import lif_state, reset_state

SENSOR = (128, 128)


# ---------------------------------------------------------------- LIF
def test_lif_spikes_above_threshold_and_resets():
    p = LIFParameters(tau_mem_s=0.1, tau_syn_s=0.05, v_th=1.0)
    st = lif_state((2, 3))
    x = torch.tensor([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0]])
    spikes = []
    for _ in range(20):
        z, st = lif_step(x, st, p, 0.025)
        spikes.append(z)
        x = torch.zeros_like(x) if len(spikes) == 1 else x
    z = torch.stack(spikes)
    assert z[:, 0].sum() == 0  # no input, no spike
    assert z[:, 1].sum() > 0
    assert set(z.unique().tolist()) <= {0.0, 1.0}
    # after a spike the membrane is reset to 0
    assert torch.all(st.v[1][z[-1, 1] > 0] == 0)


def test_surrogate_gradient_is_nonzero_and_bounded():
    v = torch.linspace(-2, 2, 41, requires_grad=True)
    spike(v, 10.0).sum().backward()
    assert torch.all(v.grad > 0) and float(v.grad.max()) <= 1.0 and float(v.grad[20]) == pytest.approx(1.0, abs=1e-5)
    assert float(v.grad[0]) == pytest.approx(1 / 21 ** 2)


def test_lif_parameter_errors():
    with pytest.raises(ValueError, match="tau_mem_s"):
        LIFParameters(tau_mem_s=0.0)
    with pytest.raises(ValueError, match="dt_s"):
        LIFParameters(tau_mem_s=0.1, tau_syn_s=0.05).check_dt(0.05)


def test_reset_state_touches_only_masked():
    st = lif_state((3, 2))
    st = type(st)(st.v + 1, st.i + 2)
    out = reset_state(st, torch.tensor([True, False, True]))
    assert out.v[1].eq(1).all() and out.v[0].eq(0).all() and out.i[2].eq(0).all() and out.i[1].eq(2).all()


# ---------------------------------------------------------------- encoding
def _events(b, x, y, t, p):
    t = torch.as_tensor(t, dtype=torch.int64)
    return Events(torch.as_tensor(b), torch.as_tensor(x), torch.as_tensor(y), t, torch.as_tensor(p, dtype=torch.int8),
                  sort=True)


def test_log_polar_encoding_conserves_events_in_the_annulus():
    enc = LogPolarEncoder(SENSOR)
    g = torch.Generator().manual_seed(0)
    n = 5000
    x = torch.randint(0, 128, (n,), generator=g)
    y = torch.randint(0, 128, (n,), generator=g)
    t = torch.randint(1, 100_001, (n,), generator=g)
    b = torch.randint(0, 3, (n,), generator=g)
    p = torch.where(torch.rand(n, generator=g) < 0.5, 1, -1)
    ev = _events(b, x, y, t, p)
    out = enc.encode(ev, 0, 100_000, 3)
    assert out.shape == (3, enc.n_sub, 2, enc.n_rho, enc.n_phi) and out.dtype == torch.float32
    inside = enc.bin_of_pixel[y * 128 + x] >= 0
    counts = out * enc.pixels_per_bin
    assert torch.allclose(counts.sum(), torch.tensor(float(inside.sum())))
    for bb in range(3):  # per batch element and polarity
        m = inside & (b == bb) & (p > 0)
        assert int(round(float(counts[bb, :, 0].sum()))) == int(m.sum())
    # time slices: quarter of the interval each
    first = inside & (t <= 25_000)
    assert int(round(float(counts[:, 0].sum()))) == int(first.sum())


def test_log_polar_empty_and_errors():
    enc = LogPolarEncoder(SENSOR)
    assert enc.encode(Events.empty(), 0, 100_000, 2).abs().sum() == 0
    assert enc.encode(None, 0, 100_000, 2).shape[0] == 2
    with pytest.raises(ValueError, match="r_min_px"):
        LogPolarEncoder(SENSOR, r_min_px=70.0, r_max_px=64.0)
    with pytest.raises(ValueError, match="without a pixel"):
        LogPolarEncoder(SENSOR, n_rho=64, n_phi=64, r_min_px=2.0)


def test_log_polar_zoom_moves_pattern_along_rho():
    """A ring of events at radius r lands in the rho bin of log r: a zoom by e^0.3 moves it by
    0.3 / (log(r_max / r_min) / n_rho) bins."""
    enc = LogPolarEncoder(SENSOR)
    drho = math.log(enc.r_max_px / enc.r_min_px) / enc.n_rho

    def ring(r):
        a = torch.linspace(0, 2 * math.pi, 400)[:-1]
        x = (64 + r * torch.cos(a)).long().clamp(0, 127)
        y = (64 + r * torch.sin(a)).long().clamp(0, 127)
        ev = _events(torch.zeros_like(x), x, y, torch.full_like(x, 50_000), torch.ones_like(x))
        c = (enc.encode(ev, 0, 100_000, 1) * enc.pixels_per_bin)[0].sum(dim=(0, 1, 3))
        return float((c * torch.arange(enc.n_rho)).sum() / c.sum())

    shift = ring(20.0 * math.exp(0.3)) - ring(20.0)
    assert abs(shift - 0.3 / drho) < 0.6


# ---------------------------------------------------------------- network
def test_network_shapes_state_and_reset():
    net = SpikingDivergenceNet(24, 24, dt_s=0.025)
    st = net.initial_state(3)
    x = torch.rand(3, 4, 2, 24, 24)
    d, st, rates = net.run_step(x, st)
    assert d.shape == (3,) and torch.isfinite(d).all()
    assert set(rates) == {"rate1", "rate2"}
    st2 = net.reset(st, torch.tensor([False, True, False]))
    assert torch.equal(st2.l1.v[0], st.l1.v[0]) and st2.l1.v[1].abs().sum() == 0 and st2.out.v[1].abs().sum() == 0
    with pytest.raises(ValueError, match="dt_s"):
        SpikingDivergenceNet(24, 24, dt_s=0.2)


def test_training_smoke_reduces_loss():
    from dvsland.estimators.snn.train import sequence_loss, train

    torch.manual_seed(0)
    net = SpikingDivergenceNet(24, 24, dt_s=0.025)
    n, k = 24, 6
    d = -torch.rand(n, 1).expand(n, k).contiguous() * 0.3 - 0.05
    x = (torch.rand(n, k, 4, 2, 24, 24) * (-d)[..., None, None, None, None] * 4).half()
    before = float(sequence_loss(net, x.float(), d, 2)[0].detach())
    hist = train(net, {"x": x, "d": d}, epochs=3, batch=8, lr=1e-2, warmup_steps=2, log=lambda *a: None)
    after = float(sequence_loss(net, x.float(), d, 2)[0].detach())
    assert len(hist["epoch"]) == 3 and math.isfinite(after) and after < before


# ---------------------------------------------------------------- estimator
def test_snn_registered_and_checkpoint_shipped():
    assert "snn" in available_estimators()
    assert DEFAULT_CHECKPOINT.is_file()


def test_snn_estimator_empty_windows_give_nan_then_finite_and_reset_by_mask():
    est = get_estimator("snn", 3, SENSOR, warmup_steps=2)
    outs = [est.update(Events.empty(), 100_000 * (k + 1)) for k in range(4)]
    assert torch.isnan(outs[0]).all() and torch.isnan(outs[1]).all()
    assert torch.isfinite(outs[2]).all() and not torch.isinf(outs[3]).any()
    est.reset(torch.tensor([True, False, False]))
    d = est.update(Events.empty(), 500_000)
    assert torch.isnan(d[0]) and torch.isfinite(d[1:]).all()
    diag = est.diagnostics()
    assert diag["steps_since_reset"].tolist() == [1, 5, 5]


def test_snn_estimator_errors(tmp_path):
    with pytest.raises(ValueError, match="checkpoint"):
        get_estimator("snn", 2, SENSOR, checkpoint=str(tmp_path / "missing.pt"))
    with pytest.raises(ValueError, match="sensor"):
        get_estimator("snn", 2, (64, 64))
    with pytest.raises(ValueError, match="warmup_steps"):
        get_estimator("snn", 2, SENSOR, warmup_steps=-1)


def test_snn_from_config():
    from dvsland.config import load_config
    from dvsland.estimators import make_estimator

    cfg = load_config(overrides=["estimator.name=snn", "estimator.snn.warmup_steps=3"])
    est = make_estimator(cfg, 2)
    assert est.warmup_steps == 3 and type(est).__name__ == "SpikingEstimator"


def test_training_sequences_follow_the_descent_law_on_held_out_terrain():
    from dvsland.config import load_config
    from dvsland.data.snn_sequences import make_sequences, training_sites

    assert training_sites((1,), "AE") == ["A~1", "E~1"]
    cfg = load_config(overrides=["camera.width_px=48", "camera.height_px=48"])
    enc = LogPolarEncoder((48, 48), n_rho=6, n_phi=8, r_min_px=6.0, r_max_px=24.0)
    data = make_sequences(cfg, enc, ["E~1"], 6, 8, seed=4, c2_max=0.6, ascent_fraction=0.3, progress=False)
    x, d, z = data["x"], data["d"].double(), data["z"].double()
    assert x.shape == (6, 8, enc.n_sub, 2, 6, 8) and x.dtype == torch.float16 and (x >= 0).all()
    assert d.shape == z.shape == (6, 8) and (z >= 60).all() and (z <= 9000).all()
    # log z changes by the integral of D: trapezoid over each step within 1 %
    dlogz = torch.log(z[:, 1:] / z[:, :-1])
    trap = 0.5 * (d[:, 1:] + d[:, :-1]) * cfg.dt_s
    assert torch.allclose(dlogz, trap, rtol=0.01, atol=1e-6)
    desc = d[:, 0] < 0
    assert (d[desc, -1] <= d[desc, 0]).all()  # |D| grows while descending
    assert (d[~desc] == d[~desc, :1]).all()  # climbs keep D


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_snn_cuda_matches_cpu():
    g = torch.Generator().manual_seed(1)
    n = 3000
    ev = _events(torch.randint(0, 2, (n,), generator=g), torch.randint(0, 128, (n,), generator=g),
                 torch.randint(0, 128, (n,), generator=g), torch.randint(1, 100_001, (n,), generator=g),
                 torch.where(torch.rand(n, generator=g) < 0.5, 1, -1))
    outs = {}
    for dev in ("cpu", "cuda"):
        est = get_estimator("snn", 2, SENSOR, device=dev, warmup_steps=0)
        est.abstain = None  # uniform noise: abstention would make both NaN; compare the network's answer
        for k in range(3):
            d = est.update(ev.to(dev), 100_000 * (k + 1))
        outs[dev] = d.cpu()
    assert torch.isfinite(outs["cpu"]).all()
    assert torch.allclose(outs["cpu"], outs["cuda"], rtol=1e-3, atol=1e-5)


def test_training_sequence_errors():
    from dvsland.config import load_config
    from dvsland.data.snn_sequences import make_sequences

    cfg = load_config()
    enc = LogPolarEncoder(SENSOR)
    for kw, name in (({"n_seq": 0}, "n_seq"), ({"d_min": 0.0}, "d_min"), ({"c2_max": 1.0}, "c2_max"),
                     ({"ascent_fraction": 1.5}, "ascent_fraction"), ({"z_min_m": 9000.0}, "z_min_m")):
        args = {"n_seq": 2, **kw}
        with pytest.raises(ValueError, match=name):
            make_sequences(cfg, enc, ["E~1"], args.pop("n_seq"), 3, progress=False, **args)


# ---------------------------------------------------------------- hard cases, activity, NIR
def test_snn_corrupt_or_foreign_checkpoint_gives_a_clear_error(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00not a checkpoint at all" * 10)
    with pytest.raises(ValueError, match="not a readable dvsland snn checkpoint") as e:
        get_estimator("snn", 2, SENSOR, checkpoint=str(bad))
    assert "weights_only" not in str(e.value) and "Unpickl" not in str(e.value)
    half = tmp_path / "half.pt"
    half.write_bytes(DEFAULT_CHECKPOINT.read_bytes()[:5000])
    with pytest.raises(ValueError, match="not a readable"):
        get_estimator("snn", 2, SENSOR, checkpoint=str(half))
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(ValueError, match="not a readable.*it has no"):
        get_estimator("snn", 2, SENSOR, checkpoint=str(foreign))


def test_snn_nan_after_many_empty_windows_and_back_with_events():
    est = get_estimator("snn", 2, SENSOR, warmup_steps=1, max_silent_steps=5)
    est.abstain = None  # uniformly random bursts: the motion test would withhold them (test_abstention.py)
    g = torch.Generator().manual_seed(0)

    def burst(k):
        n = 2000
        return _events(torch.randint(0, 2, (n,), generator=g), torch.randint(0, 128, (n,), generator=g),
                       torch.randint(0, 128, (n,), generator=g), torch.randint(k * 100_000 + 1, (k + 1) * 100_000 + 1,
                                                                            (n,), generator=g),
                       torch.where(torch.rand(n, generator=g) < 0.5, 1, -1))
    for k in range(3):
        d = est.update(burst(k), (k + 1) * 100_000)
    assert torch.isfinite(d).all() and (est.confidence() > 0).all()
    for k in range(3, 3 + 4):
        d = est.update(Events.empty(), (k + 1) * 100_000)
    assert torch.isfinite(d).all()  # 4 silent updates < 5
    for k in range(7, 40):
        d = est.update(Events.empty(), (k + 1) * 100_000)
        assert torch.isnan(d).all() and (est.confidence() == 0).all()
    d = est.update(burst(40), 41 * 100_000)
    assert torch.isfinite(d).all()


def test_snn_events_off_the_sensor_rule():
    """Through update, events off the sensor or the batch are a clear error (the estimators' input
    gate); the encoder itself ignores them and counts them, never indexing outside its table."""
    ev = _events(torch.tensor([0, 0, 1, 1, 5]), torch.tensor([10, 128, 300, 20, 3]),
                 torch.tensor([10, 5, 5, -1, 3]), torch.tensor([10, 20, 30, 40, 50]), torch.tensor([1, -1, 1, 1, 1]))
    est = get_estimator("snn", 2, SENSOR, warmup_steps=0)
    with pytest.raises(ValueError, match="'b' must be in"):
        est.update(ev, 100_000)
    x = est.encoder.encode(ev, 0, 100_000, 2)
    assert x.shape[0] == 2 and est.encoder.dropped == 4 and torch.isfinite(x).all()


def test_snn_reports_spikes_and_synaptic_operations():
    est = get_estimator("snn", 2, SENSOR, warmup_steps=0)
    g = torch.Generator().manual_seed(2)
    n = 4000
    ev = _events(torch.zeros(n, dtype=torch.int64), torch.randint(0, 128, (n,), generator=g),
                 torch.randint(0, 128, (n,), generator=g), torch.randint(1, 100_001, (n,), generator=g),
                 torch.where(torch.rand(n, generator=g) < 0.5, 1, -1))
    for k in range(3):
        ev.t += 100_000 * (k > 0)
        est.update(ev, (k + 1) * 100_000)
    diag = est.diagnostics()
    c1, _ = est.model.channels
    assert diag["spikes"][0] > 0 and diag["synops"][0] >= diag["spikes"][0]
    assert diag["synops"][1] == 0 and diag["spikes"][1] == 0  # element 1 saw nothing, stays silent
    # every input bin with events costs c1 x 5 x 3 synaptic operations
    assert float(diag["synops"][0]) % 1 == 0 or diag["synops"][0] > c1 * 15


def test_snn_nir_round_trip_reproduces_the_network(tmp_path):
    pytest.importorskip("nir")
    pytest.importorskip("nirtorch")
    import nir

    from dvsland.estimators.snn import load_checkpoint
    from dvsland.estimators.snn.nir_export import export_nir, from_nir, nir_input

    model, _, _ = load_checkpoint()
    path = export_nir(model, tmp_path / "snn.nir")
    graph = nir.read(str(path))  # type-checked on read: the shapes are consistent
    assert {"conv1", "lif1", "conv2", "lif2", "readout", "li"} <= set(graph.nodes)
    assert graph.metadata["dt_s"] == pytest.approx(model.dt_s)
    back = from_nir(path)
    g = torch.Generator().manual_seed(0)
    B, steps = 3, 24
    x = (torch.rand(steps, B, 2, model.n_rho, model.n_phi, generator=g) < 0.06).float() \
        * torch.rand(steps, B, 2, model.n_rho, model.n_phi, generator=g) * 0.5
    st, st2, spikes = model.initial_state(B), None, 0.0
    with torch.no_grad():
        for k in range(steps):
            d, st, r = model(x[k], st)
            out, st2 = back(nir_input(x[k], model), st2)
            spikes += float(r["rate1"].sum() + r["rate2"].sum())
            assert torch.allclose(out[:, 0], d, rtol=1e-4, atol=1e-7), (k, out[:, 0], d)
    assert spikes > 0  # the comparison covered a spiking network, not a silent one


# ---------------------------------------------------------------- dispersed data, held-out type, fast path
def test_training_sites_hold_out_a_site_type():
    from dvsland.estimators.snn.data import SITE_TYPES, training_sites

    assert sorted("".join(SITE_TYPES.values())) == list("ABCDEFGHI")
    for kind, letters in SITE_TYPES.items():
        names = training_sites((1, 2), hold_out_type=kind)
        assert len(names) == 2 * (9 - len(letters))
        assert not any(n[0] in letters for n in names)
    with pytest.raises(ValueError, match="hold_out_type"):
        training_sites(hold_out_type="volcanic")


def test_dispersed_training_sequences_draw_sun_and_sensor_and_skip_the_held_out_type():
    from dvsland.config import load_config
    from dvsland.data.snn_sequences import SITE_TYPES, make_sequences, training_sites

    cfg = load_config(overrides=["camera.width_px=48", "camera.height_px=48"])
    disp = load_config("configs/montecarlo.yaml").dispersion
    enc = LogPolarEncoder((48, 48), n_rho=6, n_phi=8, r_min_px=6.0, r_max_px=24.0, n_sub=2)
    sites = training_sites((1,), "ADG", hold_out_type="craters_rocks")
    data = make_sequences(cfg, enc, sites, 6, 5, seed=3, dispersion=disp, sun_step_deg=3.0, progress=False)
    assert data["x"].shape == (6, 5, 2, 2, 6, 8) and torch.isfinite(data["x"].float()).all()
    assert not any(data["sites"][int(i)][0] in SITE_TYPES["craters_rocks"] for i in data["site"])
    dr = data["dispersed"]
    assert set(dr) == {"sun_elevation_deg", "threshold_scale", "mismatch_sigma", "background_rate_hz", "refractory_us"}
    assert all(v.shape == (6,) for v in dr.values())
    assert set(dr["sun_elevation_deg"].tolist()) <= {12.0, 15.0, 18.0}
    assert ((dr["threshold_scale"] >= 0.85) & (dr["threshold_scale"] <= 1.15)).all()
    assert ((dr["refractory_us"] >= 5.0) & (dr["refractory_us"] <= 50.0)).all()
    assert len(set(dr["threshold_scale"].tolist())) == 6  # drawn per sequence
    # same seed, same data (draws and events); without dispersion nothing is drawn
    again = make_sequences(cfg, enc, sites, 6, 5, seed=3, dispersion=disp, sun_step_deg=3.0, progress=False)
    assert torch.equal(again["x"], data["x"]) and np.array_equal(again["dispersed"]["refractory_us"], dr["refractory_us"])
    plain = make_sequences(cfg, enc, sites, 6, 5, seed=3, progress=False)
    assert plain["dispersed"] == {} and not torch.equal(plain["x"], data["x"])


def test_inference_lif_step_equals_training_step_bit_for_bit():
    from dvsland.estimators.snn.lif import lif_step_inference

    g = torch.Generator().manual_seed(2)
    p = LIFParameters(tau_mem_s=0.1, tau_syn_s=0.05, v_th=1.0)
    st = lif_state((4, 3, 5))
    st = type(st)(torch.rand(4, 3, 5, generator=g) * 1.5, torch.randn(4, 3, 5, generator=g))
    k_mem = torch.rand(3, 1, generator=g) * 0.5
    x = torch.randn(4, 3, 5, generator=g)
    z_a, s_a = lif_step(x, st, p, 0.025, k_mem)
    z_b, s_b = lif_step_inference(x, st, p, 0.025, k_mem)
    assert torch.equal(z_a, z_b) and torch.equal(s_a.v, s_b.v) and torch.equal(s_a.i, s_b.i)
    assert 0 < float(z_a.sum()) < z_a.numel()  # both cases present
    # the whole network: no_grad (fast path) equals the autograd path
    net = SpikingDivergenceNet(24, 24, dt_s=0.05, channels=(8, 16))
    xs = torch.rand(2, 3, 2, 2, 24, 24, generator=g) * 0.2
    outs = []
    for grad in (True, False):
        with torch.set_grad_enabled(grad):
            s = net.initial_state(2)
            for k in range(3):
                d, s, _ = net.run_step(xs[:, k], s)
            outs.append(d.detach())
    assert torch.equal(outs[0], outs[1])


def test_small_network_two_slices_shapes_and_reset_by_mask():
    net = SpikingDivergenceNet(24, 24, dt_s=0.05, channels=(8, 16))
    st = net.initial_state(3)
    assert st.l1.v.shape == (3, 8, 24, 24) and st.l2.v.shape == (3, 16, 12, 24)
    assert all(torch.isfinite(k).all() and (k > 0).all() and (k <= 0.5).all() for k in net._time_constants().values())
    d, st, rates = net.run_step(torch.rand(3, 2, 2, 24, 24), st)
    assert d.shape == (3,) and torch.isfinite(d).all() and rates["rate1"].shape == (3,)
    st2 = net.reset(st, torch.tensor([True, False, False]))
    assert st2.l2.i[0].abs().sum() == 0 and torch.equal(st2.l2.i[1:], st.l2.i[1:])


def test_training_crop_steps():
    from dvsland.estimators.snn.train import train

    net = SpikingDivergenceNet(24, 24, dt_s=0.05, channels=(8, 16))
    n, k = 8, 10
    d = -torch.full((n, k), 0.1)
    x = (torch.rand(n, k, 2, 2, 24, 24) * 0.2).half()
    hist = train(net, {"x": x, "d": d}, epochs=1, batch=4, warmup_steps=2, crop_steps=4, log=lambda *a: None)
    assert len(hist["epoch"]) == 1 and math.isfinite(hist["train_loss"][0])
    with pytest.raises(ValueError, match="crop_steps"):
        train(net, {"x": x, "d": d}, epochs=1, crop_steps=2, warmup_steps=2, log=lambda *a: None)
