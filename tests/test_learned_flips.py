"""Test-time mirroring of the learned estimator (``estimator.learned.flips``)."""

from __future__ import annotations

import pytest
import torch

from dvsland.estimators.learned.flips import check_flips, mirrored_copies, pool_copies, run_copies
from dvsland.events import Events

from test_learned import _checkpoint, _events, _plain, ckpt  # noqa: F401 - ckpt: the fixture of a small CNN checkpoint


def _mirror(ev: Events, W=128, H=128, x=False, y=False, transpose=False) -> Events:
    ex, ey = ev.x, ev.y
    if x:
        ex = W - 1 - ex
    if y:
        ey = H - 1 - ey
    if transpose:
        ex, ey = ey, ex
    return Events(b=ev.b, x=ex, y=ey, t=ev.t, p=ev.p)


@pytest.fixture
def spiking(tmp_path):
    torch.manual_seed(1)
    path = tmp_path / "s.pt"
    _checkpoint(path, "spiking", n_bins=6, pool_px=4, settings={"slice_dt_s": 0.1 / 6})
    return path


def test_mirrored_copies_order_and_shape():
    v = torch.arange(2 * 3 * 4 * 4, dtype=torch.float32).view(2, 3, 4, 4)
    assert len(mirrored_copies(v, 1)) == 1 and mirrored_copies(v, 1)[0] is v
    expect = [v, v.flip((-2, -1)), v.flip(-1), v.flip(-2)]
    expect += [e.transpose(-2, -1) for e in expect]
    for n in (2, 4, 8):
        got = mirrored_copies(v, n)
        assert len(got) == n and all(torch.equal(g, e) for g, e in zip(got, expect))


def test_pool_copies_is_the_mixture_of_the_copies():
    mu = torch.tensor([[0.0, 1.0], [2.0, 3.0]])  # (2 copies, 2 rows)
    log_var = torch.log(torch.tensor([[1.0, 4.0], [3.0, 2.0]]))
    spikes = torch.tensor([[1.0, 2.0], [10.0, 20.0]])
    m, lv, a = pool_copies(mu, log_var, spikes)
    assert torch.allclose(m, torch.tensor([1.0, 2.0]))
    assert torch.allclose(torch.exp(lv), torch.tensor([(1 + 3) / 2 + 1.0, (4 + 2) / 2 + 1.0]))
    assert torch.equal(a, torch.tensor([11.0, 22.0]))


def test_run_copies_calls_the_network_once_per_copy():
    v = torch.rand(3, 2, 4, 4)
    calls = []

    def net(x, scale):
        calls.append(x)
        return x.mean(dim=(1, 2, 3)) * scale, torch.zeros(3), torch.ones(3)

    mu, log_var, act = run_copies(net, v, 4, 2.0)
    assert len(calls) == 4 and all(c.shape == v.shape for c in calls)
    assert torch.allclose(mu, 2.0 * v.mean(dim=(1, 2, 3))) and torch.equal(act, torch.full((3,), 4.0))
    assert run_copies(net, v, 1, 1.0)[0].shape == (3,) and len(calls) == 5


@pytest.mark.parametrize("flips", [0, 3, 16, "8"])
def test_bad_flips_name_the_parameter(ckpt, flips):
    with pytest.raises(ValueError, match=r"estimator\.learned\.flips must be one of 1, 2, 4, 8"):
        _plain("learned", 2, (128, 128), checkpoint=str(ckpt), flips=flips)


def test_flips_need_a_symmetric_canvas(tmp_path):
    _checkpoint(tmp_path / "r.pt", sensor=(128, 96))
    with pytest.raises(ValueError, match=r"flips = 8 .* square"):
        _plain("learned", 2, (128, 96), checkpoint=str(tmp_path / "r.pt"), flips=8)
    assert _plain("learned", 2, (128, 96), checkpoint=str(tmp_path / "r.pt"), flips=4).params.flips == 4
    with pytest.raises(ValueError, match=r"flips = 2 .* multiples of pool_px = 3"):
        check_flips(2, (128, 128), 3)


def test_config_refuses_other_flips():
    from dvsland.config import ConfigError, load_config

    with pytest.raises(ConfigError, match=r"estimator\.learned\.flips"):
        load_config("paper", overrides=["estimator.learned.flips=3"])


@pytest.mark.parametrize("flips", [2, 4, 8])
def test_flips_are_the_mean_of_the_mirrored_windows(ckpt, flips):
    """Against the reference: the estimate of ``flips`` copies is -exp of the mean log|D| that the
    plain estimator gives on the mirrored events, one by one."""
    ev = _events(3, 900)
    mirrors = [{}, {"x": True, "y": True}, {"x": True}, {"y": True}]
    mirrors += [{**m, "transpose": True} for m in mirrors]
    logs = [torch.log(-_plain("learned", 3, (128, 128), checkpoint=str(ckpt), min_events=1, fast="").update(
        _mirror(ev, **m), 100_000)) for m in mirrors[:flips]]
    want = -torch.exp(torch.stack(logs).mean(0))
    got = _plain("learned", 3, (128, 128), checkpoint=str(ckpt), min_events=1, flips=flips).update(ev, 100_000)
    assert torch.allclose(got, want, rtol=1e-5)
    assert torch.isfinite(got).all() and (got < 0).all()


def test_eight_flips_do_not_see_a_mirroring(ckpt):
    """The pool over the whole symmetry group is invariant: a mirrored scene gives the same D_hat."""
    ev = _events(2, 700, seed=3)
    est = [_plain("learned", 2, (128, 128), checkpoint=str(ckpt), min_events=1, flips=8) for _ in range(2)]
    a = est[0].update(ev, 100_000)
    b = est[1].update(_mirror(ev, x=True, transpose=True), 100_000)
    assert torch.allclose(a, b, rtol=1e-5)
    one = _plain("learned", 2, (128, 128), checkpoint=str(ckpt), min_events=1, fast="")
    assert not torch.allclose(one.update(ev, 100_000), a, rtol=1e-5)  # the pool is not the window alone


def test_spiking_flips_sum_the_activity_and_keep_nan_rows(spiking):
    ev = _events(3, 800, skip=(1,))
    plain = [_plain("learned", 3, (128, 128), checkpoint=str(spiking), min_events=5) for _ in range(2)]
    plain[0].update(ev, 100_000)
    plain[1].update(_mirror(ev, x=True, y=True), 100_000)
    est = _plain("learned", 3, (128, 128), checkpoint=str(spiking), min_events=5, flips=2)
    d = est.update(ev, 100_000)
    assert torch.isnan(d[1]) and torch.isfinite(d[[0, 2]]).all()
    diag, parts = est.diagnostics(), [p.diagnostics() for p in plain]
    for k in ("spikes", "synops"):
        assert torch.allclose(diag[k][[0, 2]], (parts[0][k] + parts[1][k])[[0, 2]])
    assert diag["confidence"][1] == 0
