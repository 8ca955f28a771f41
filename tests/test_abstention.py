"""Abstention, part of every estimator's contract: on windows without a moving scene (uniform
sensor noise at 300, 1 000 and 3 000 events per 0.1 s on 128 x 128, a static scene whose only
events are noise, a global flicker, empty windows) every shipped estimator that takes events gives
NaN or a confidence <= 0.1 from the first second on; on a rendered descent the motion-evidence
test leaves every estimate and confidence exactly as they were (factor 1), and the estimators that
were confident there stay so. Plug-ins get the same test through the base class."""

from __future__ import annotations

import pytest
import torch

from dvsland.config import load_config
from dvsland.estimators import DivergenceEstimator, get_estimator
from dvsland.estimators.abstain import EVIDENCE_KEY, AbstainParams, motion_evidence
from dvsland.estimators.factory import estimator_params
from dvsland.events import Events

W = H = 128
DT_US = 100_000
STEPS = 20  # 2 s; the target applies after the first second (steps 11..20)
B = 3  # descents per batch: the seeds of one window kind run side by side

#: (name, extra params): every shipped estimator that takes events, both shipped learned models
SHIPPED = [("cmax", {}), ("dpr", {}), ("dpr", {"baseline_steps": 5}), ("snn", {}), ("learned", {}),
           ("learned", {"checkpoint": "spiking"}), ("learned", {"checkpoint": "cnn_landing"}),
           ("learned", {"checkpoint": "cnn_wide"}), ("learned", {"checkpoint": "cnn_dagger"}),
           ("learned", {"checkpoint": "spiking8"}), ("learned", {"checkpoint": "cnn_both"}),
           ("learned", {"checkpoint": "spiking8_both"}), ("learned", {"checkpoint": "spiking8_dagger"}),
           ("learned", {"checkpoint": "spiking8_px2"}), ("learned", {"checkpoint": "cnn_both", "flips": 8}),
           ("learned", {"checkpoint": "spiking8_px2", "flips": 2}), ("learned", {"checkpoint": "spiking8_px2_more"}),
           ("learned", {"checkpoint": "spiking8_px2_more", "flips": 8})]
IDS = ["cmax", "dpr", "dpr5", "snn", "learned-cnn", "learned-spiking", "learned-cnn-landing", "learned-cnn-wide",
       "learned-cnn-dagger", "learned-spiking8", "learned-cnn-both", "learned-spiking8-both",
       "learned-spiking8-dagger", "learned-spiking8-px2", "learned-cnn-both-flips8", "learned-spiking8-px2-flips2",
       "learned-spiking8-px2-more", "learned-spiking8-px2-more-flips8"]
#: and the combination of two of them (its members run the test; it abstains where they all do)
WITH_FUSED, IDS_FUSED = SHIPPED + [("fused", {})], IDS + ["fused-cmax-learned"]


def build(name: str, extra: dict, batch: int = B, cfg=None) -> DivergenceEstimator:
    cfg = cfg or load_config("paper")
    kw = estimator_params(cfg, name)
    kw.update(extra, dt_s=cfg.dt_s, principal_point_px=cfg.camera.principal_point_px)
    if name in ("cmax", "snn"):
        kw["seed"] = 0
    return get_estimator(name, batch, (cfg.camera.width_px, cfg.camera.height_px), "cpu", **kw)


def noise_window(n: int, seed: int, k: int, batch: int = B) -> Events:
    """``n`` uniformly random events per descent in step ``k``'s window ((k-1) dt, k dt], random
    polarity; descent b draws from seed ``seed + b``."""
    g = torch.Generator().manual_seed(1_000_003 * seed + k)
    N = n * batch
    b = torch.arange(batch).repeat_interleave(n)
    t = (k - 1) * DT_US + 1 + torch.randint(0, DT_US, (N,), generator=g)
    p = (torch.randint(0, 2, (N,), generator=g) * 2 - 1).to(torch.int8)
    return Events(b, torch.randint(0, W, (N,), generator=g), torch.randint(0, H, (N,), generator=g), t, p, sort=True)


def empty_window(k: int) -> Events:
    z = torch.zeros(0, dtype=torch.int64)
    return Events(z, z, z, z, z.to(torch.int8))


def flicker_window(seed: int, k: int, batch: int = B) -> Events:
    """Global illumination flicker: every pixel ON once in the first half of the window, OFF once in
    the second, at random times within its half; no motion."""
    g = torch.Generator().manual_seed(7 * seed + k)
    P = W * H
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    x, y = xx.reshape(-1).repeat(2 * batch), yy.reshape(-1).repeat(2 * batch)
    b = torch.arange(batch).repeat_interleave(2 * P)
    half = torch.arange(2).repeat_interleave(P).repeat(batch)
    t = (k - 1) * DT_US + 1 + half * (DT_US // 2) + torch.randint(0, DT_US // 2, (2 * P * batch,), generator=g)
    return Events(b, x, y, t, (1 - 2 * half).to(torch.int8), sort=True)


_STATIC = {}


def static_noise_window(seed: int, k: int) -> Events:
    """A static scene (site A at 1 km, one frame held) through the noisy pixel of
    ``configs/realistic_sensor.yaml`` without denoising, plus 300 uniform noise events per window:
    the only events are noise (shot noise, leak, hot pixels, background)."""
    from dvsland.stages import build_event_source

    key = seed
    if key not in _STATIC:
        cfg = load_config("realistic_sensor", ["emulator.denoise=none"])
        src = build_event_source(cfg, ["A"], seed=seed)
        z, idx = torch.full((B,), 1000.0, dtype=torch.float64), torch.zeros(B, dtype=torch.int64)
        frames = src.render(z, idx)
        src.emulator.reset(frames, 0)
        _STATIC[key] = [src.emulator.step(frames, j * DT_US) for j in range(1, STEPS + 1)]
    ev, extra = _STATIC[key][k - 1], noise_window(300, seed, k)
    cat = [torch.cat([getattr(ev, f), getattr(extra, f)]) for f in "bxytp"]
    return Events(*cat, sort=True)


KINDS = {"noise300": lambda s, k: noise_window(300, s, k), "noise1000": lambda s, k: noise_window(1000, s, k),
         "noise3000": lambda s, k: noise_window(3000, s, k), "empty": lambda s, k: empty_window(k),
         "flicker": flicker_window, "static_noise": static_noise_window}


def max_confidence_after_first_second(est: DivergenceEstimator, window, seed: int) -> float:
    """The largest confidence among finite estimates of steps 11..20 (0 when all are NaN)."""
    est.reset()
    worst = 0.0
    for k in range(1, STEPS + 1):
        d = est.update(window(seed, k), k * DT_US)
        c = est.confidence()
        assert d.shape == (est.batch_size,) and c.shape == (est.batch_size,)
        if k > 10:
            worst = max(worst, float(torch.where(torch.isfinite(d), c, torch.zeros_like(c)).max()))
    return worst


@pytest.mark.parametrize("name,extra", WITH_FUSED, ids=IDS_FUSED)
@pytest.mark.parametrize("kind", list(KINDS))
def test_every_estimator_abstains_without_motion(name, extra, kind):
    est = build(name, extra)
    for seed in ((0,) if kind == "flicker" else (0, 1)):  # a flicker window holds 2 events per pixel: one seed
        worst = max_confidence_after_first_second(est, KINDS[kind], seed)
        assert worst <= 0.1, f"{name}{extra} on {kind} (seed {seed}): confidence {worst:.2f} after the first second"


def test_without_the_test_the_noise_gets_through():
    """The control of the test above: with ``abstain = None`` cmax and the CNN are confident on
    noise (what the shipped estimators did before), so the noise windows do test something."""
    worst = []
    for name, extra in (("cmax", {}), ("learned", {})):
        est = build(name, extra)
        est.abstain = None
        worst.append(max_confidence_after_first_second(est, KINDS["noise3000"], 0))
    assert max(worst) > 0.3, worst


# ------------------------------------------------------------------ the statistic itself
def test_motion_evidence_separates_noise_flicker_and_structure():
    """Noise and flicker get factor 0, edges of a moving pattern factor 1, and a window with fewer
    than min_events events is not judged (factor 1)."""
    p = AbstainParams()
    noise = noise_window(1000, 3, 1, batch=4)
    ev = motion_evidence(noise, 4, (W, H), DT_US)
    assert (ev.factor == 0).all() and (ev.clustering - 1).abs().max() < 0.3 and ev.neighbours.abs().max() < p.neighbours_none
    fl = motion_evidence(flicker_window(0, 1, batch=2), 2, (W, H), DT_US)
    assert (fl.factor == 0).all() and (fl.flicker > 0.8).all()
    # events on the edges of squares (a textured scene): clustered and with neighbours
    g = torch.Generator().manual_seed(0)
    xs, ys = [], []
    for cx, cy in torch.randint(10, 118, (12, 2), generator=g).tolist():
        for d in range(-6, 7):
            xs += [cx + d, cx + d, cx - 6, cx + 6]
            ys += [cy - 6, cy + 6, cy + d, cy + d]
    x, y = torch.tensor(xs).clamp(0, W - 1), torch.tensor(ys).clamp(0, H - 1)
    n = x.numel()
    t = torch.randint(1, DT_US + 1, (n,), generator=g)
    pol = (torch.randint(0, 2, (n,), generator=g) * 2 - 1).to(torch.int8)
    edges = motion_evidence(Events(torch.zeros(n, dtype=torch.int64), x, y, t, pol, sort=True), 1, (W, H), DT_US)
    assert n >= p.full_events and edges.factor.item() == 1.0 and edges.clustering.item() > 2
    few = motion_evidence(noise_window(p.min_events - 1, 0, 1, batch=1), 1, (W, H), DT_US)
    assert few.factor.item() == 1.0
    assert (motion_evidence(None, 3, (W, H), DT_US).factor == 1).all()


def test_dense_windows_are_judged_by_what_can_show_structure():
    """Where most pixels are active (a dense zoom: about 3 events per pixel and step) the active-pixel
    statistics cannot show structure, and such a window used to be abstained: those two tests fade out
    from an active share of 0.6 to 0.75. Dense uniform noise (a share of 0.26) is still abstained, and
    so is a global flicker, every pixel active (the flicker test stays)."""
    from dvsland.evaluate import ZoomTextureFrames
    from dvsland.events import EventEmulator

    src = ZoomTextureFrames(1, (160, 160), 60.0, ground_m=300.0, seed=1)
    idx = torch.zeros(1, dtype=torch.long)
    emu = EventEmulator()
    emu.reset(src(torch.tensor([500.0]), idx), 0)
    ev = emu.step(src(torch.tensor([485.0]), idx), DT_US)
    active = torch.zeros(160 * 160).index_fill_(0, ev.y * 160 + ev.x, 1.0).mean()
    assert active > 0.75 and len(ev) > 50_000
    off = AbstainParams(saturated_from=1.01, saturated_full=1.02)  # the test without the fade
    assert motion_evidence(ev, 1, (160, 160), DT_US, off).factor.item() == 0.0
    assert motion_evidence(ev, 1, (160, 160), DT_US).factor.item() == 1.0
    dense_noise = noise_window(5000, 2, 1, batch=2)  # 0.3 events per pixel on 128 x 128
    assert (motion_evidence(dense_noise, 2, (W, H), DT_US).factor == 0).all()
    assert (motion_evidence(flicker_window(1, 1, batch=1), 1, (W, H), DT_US).factor == 0).all()
    with pytest.raises(ValueError, match="saturated_from must be < abstain.saturated_full"):
        motion_evidence(None, 1, (W, H), DT_US, AbstainParams(saturated_from=0.8, saturated_full=0.7))


def test_rows_are_judged_independently():
    """Noise in one descent does not touch its neighbour's factor (batched, no mixing)."""
    a = noise_window(2000, 0, 1, batch=2)
    fl = flicker_window(0, 1, batch=1)
    ev = Events(torch.cat([a.b, fl.b + 2]), torch.cat([a.x, fl.x]), torch.cat([a.y, fl.y]), torch.cat([a.t, fl.t]),
                torch.cat([a.p, fl.p]), sort=True)
    out = motion_evidence(ev, 4, (W, H), DT_US)
    assert out.factor.tolist() == [0.0, 0.0, 0.0, 1.0]  # row 3 has no events: not judged
    assert out.n_events.tolist() == [2000, 2000, 2 * W * H, 0]


# ------------------------------------------------------------------ plug-ins
class _ObjectApiOnly(DivergenceEstimator):
    """A plug-in with the object API alone: always says -0.1 1/s with confidence 0.9."""

    def reset(self, mask=None):
        self._d = torch.full((self.batch_size,), float("nan"))

    def update(self, events, t_us, truth=None):
        self._d = torch.full((self.batch_size,), -0.1)
        return self._d.clone()

    def confidence(self):
        return torch.where(torch.isfinite(self._d), torch.full_like(self._d, 0.9), torch.zeros_like(self._d))


def test_object_api_plugin_gets_the_test():
    est = _ObjectApiOnly(2, (W, H))
    est.reset()
    d = est.update(noise_window(1000, 0, 1, batch=2), DT_US)
    assert torch.isnan(d).all() and (est.confidence() == 0).all()
    est.abstain = None  # turned off for this instance: the plug-in's own answer
    d = est.update(noise_window(1000, 0, 2, batch=2), 2 * DT_US)
    assert (d == -0.1).all() and (est.confidence() == 0.9).all()


def test_oracle_is_not_gated():
    est = get_estimator("oracle", 2, (W, H))
    from dvsland.estimators.base import Truth

    tr = Truth(torch.tensor([100.0, 200.0], dtype=torch.float64), torch.tensor([-5.0, -5.0], dtype=torch.float64))
    d = est.update(None, DT_US, tr)
    assert torch.isfinite(d).all() and EVIDENCE_KEY not in est.diagnostics()


# ------------------------------------------------------------------ real motion: nothing moves
@pytest.fixture(scope="module")
def descent_windows():
    """The events of 3 s of the closed-form descent of sites A and G (paper config) from 2 km
    (A) and 1 km (G): real motion, rendered and emulated."""
    from dvsland.dynamics import closed_form_state
    from dvsland.stages import build_event_source

    cfg = load_config("paper")
    specs = {s.name: s for s in cfg.simulation.sites}
    src = build_event_source(cfg, ["A", "G"])
    idx = torch.arange(2)
    t0 = [(2000.0, "A"), (1000.0, "G")]
    from dvsland.dynamics import closed_form_time_to_altitude

    starts = [closed_form_time_to_altitude(z, specs[s].z0_m, specs[s].v0_mps, cfg.controller.c2) for z, s in t0]
    zs, vs = [], []
    for k in range(31):
        zv = [closed_form_state(st + k * cfg.dt_s, specs[s].z0_m, specs[s].v0_mps, cfg.controller.c2) for st, (_, s)
              in zip(starts, t0)]
        zs.append([float(z) for z, _ in zv])
        vs.append([float(v) for _, v in zv])
    z = torch.tensor(zs, dtype=torch.float64)
    src.reset(z[0], idx, 0)
    return [src.step(z[k], idx, k * DT_US)[1] for k in range(1, 31)], z, torch.tensor(vs, dtype=torch.float64)


@pytest.mark.parametrize("name,extra", SHIPPED, ids=IDS)
def test_real_motion_is_untouched(name, extra, descent_windows):
    """On rendered descent windows the factor is 1 at every step, and the estimates and confidences
    are bit for bit those of the same estimator with the test off; where an estimator was
    confident (cmax, the CNN) it still is (> 0.3: what the realistic preset's filter takes is 0.15)."""
    from dvsland.estimators.base import Truth

    windows, z, v = descent_windows
    on, off = build(name, extra, batch=2), build(name, extra, batch=2)
    off.abstain = None
    s_on, s_off = on.init_state(), off.init_state()
    best = 0.0
    for k, ev in enumerate(windows, start=1):
        tr = Truth(z[k], v[k])
        s_on, o_on = on.step_state(s_on, ev, k * DT_US, tr)
        s_off, o_off = off.step_state(s_off, ev, k * DT_US, tr)
        assert (o_on.diagnostics[EVIDENCE_KEY] == 1).all(), f"step {k}: {o_on.diagnostics[EVIDENCE_KEY]}"
        assert EVIDENCE_KEY not in o_off.diagnostics
        assert torch.equal(torch.isnan(o_on.d_hat), torch.isnan(o_off.d_hat))
        assert torch.equal(torch.nan_to_num(o_on.d_hat), torch.nan_to_num(o_off.d_hat))
        assert torch.equal(o_on.confidence, o_off.confidence)
        if k > 10:
            best = max(best, float(o_on.confidence.max()))
    if name == "cmax" or (name == "learned" and not extra):
        assert best > 0.3, f"{name}: confidence on real motion {best:.2f}"


def test_bad_thresholds_name_the_field():
    with pytest.raises(ValueError, match="abstain.clustering_none must be < abstain.clustering_full"):
        motion_evidence(None, 1, (W, H), DT_US, AbstainParams(clustering_none=2.0, clustering_full=1.0))
    with pytest.raises(ValueError, match=r"abstain.cell_px must be in \[2, 1024\]"):
        motion_evidence(None, 1, (W, H), DT_US, AbstainParams(cell_px=1))


def test_config_section_tunes_or_turns_off_the_test():
    """estimator.abstain: defaults leave the class's setting, enabled=false turns it off, a tuned
    threshold is passed on, and a contradictory pair is refused naming the keys."""
    from dvsland.config import load_config
    from dvsland.estimators.abstain import DEFAULT_ABSTAIN
    from dvsland.stages import build_estimator

    cfg = load_config("paper", ["estimator.name=cmax"])
    assert build_estimator(cfg, 2).abstain == DEFAULT_ABSTAIN
    off = load_config("paper", ["estimator.name=cmax", "estimator.abstain.enabled=false"])
    assert build_estimator(off, 2).abstain is None
    tuned = load_config("paper", ["estimator.name=cmax", "estimator.abstain.min_events=500",
                                  "estimator.abstain.full_events=800"])
    assert build_estimator(tuned, 2).abstain.min_events == 500
    bad = load_config("paper", ["estimator.name=cmax", "estimator.abstain.clustering_none=2.0"])
    with pytest.raises(ValueError, match=r"estimator\.abstain\.clustering_none"):
        build_estimator(bad, 2)
    oracle = load_config("paper", ["estimator.name=oracle"])
    assert not getattr(build_estimator(oracle, 2), "needs_events", True)  # no events: never judged
