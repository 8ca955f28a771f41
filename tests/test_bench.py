"""dvsland.bench: Wilson interval, Pareto front, stage timing, the report folder, the CLI."""

from __future__ import annotations

import json
import math

import pytest
import torch

from dvsland.bench import pareto_front, parse_what, time_stages, wilson_interval
from dvsland.cli.main import build_parser, main
from dvsland.config import load_config


class TestWilson:
    def test_known_values(self):
        # closed forms: k = 0 -> (0, z^2 / (n + z^2)); k = n -> (n / (n + z^2), 1)
        z = 1.959963984540054
        lo, hi = wilson_interval(0, 10)
        assert lo == 0.0 and hi == pytest.approx(z * z / (10 + z * z))
        lo, hi = wilson_interval(10, 10)
        assert hi == 1.0 and lo == pytest.approx(10 / (10 + z * z))
        lo, hi = wilson_interval(13, 18)  # textbook value: 0.491 - 0.875
        assert lo == pytest.approx(0.4913, abs=1e-3) and hi == pytest.approx(0.8750, abs=1e-3)

    def test_contains_p_and_narrows(self):
        for k, n in [(1, 3), (5, 9), (50, 90)]:
            lo, hi = wilson_interval(k, n)
            assert lo < k / n < hi
        assert (wilson_interval(50, 100)[1] - wilson_interval(50, 100)[0]
                < wilson_interval(5, 10)[1] - wilson_interval(5, 10)[0])
        assert all(math.isnan(x) for x in wilson_interval(0, 0))  # no trials, no interval (docs/campaigns.md)

    @pytest.mark.parametrize("k,n", [(-1, 3), (4, 3), (1, -1)])
    def test_bad_input(self, k, n):
        with pytest.raises(ValueError, match="successes"):
            wilson_interval(k, n)


def test_pareto_front():
    pts = [(10.0, 0.5), (1.0, 0.9), (5.0, 0.2), (20.0, 0.2), (3.0, float("nan")), (50.0, 0.1)]
    assert pareto_front(pts) == [1, 2, 5]
    assert pareto_front([]) == []


def test_parse_what():
    assert parse_what([]) == ["tradeoff", "closed_loop", "scaling", "economies"]
    assert parse_what(["closed-loop", "render"]) == ["closed_loop", "render"]
    assert "sim" in parse_what(["all"])
    with pytest.raises(ValueError, match="unknown benchmark 'nope'"):
        parse_what(["nope"])


class _Frames:
    """A smooth zooming texture: (altitude (B,), site (B,)) -> (B, 32, 32)."""

    def __call__(self, z, idx):
        y, x = torch.meshgrid(torch.arange(32.0, device=z.device), torch.arange(32.0, device=z.device), indexing="ij")
        s = (1000.0 / z.double()).view(-1, 1, 1)
        return (1.2 + torch.sin((x - 16) * 0.4 * s + idx.view(-1, 1, 1)) * torch.cos((y - 16) * 0.3 * s)).float()


def _small_cfg():
    cfg = load_config(None, ["camera.width_px=32", "camera.height_px=32", "estimator.dpr.n_min=3"])
    return cfg


@pytest.mark.parametrize("estimator", ["dpr", "oracle"])
def test_time_stages_keys_and_values(estimator, device):
    cfg = _small_cfg()
    r = time_stages(cfg, 5, device, estimator, n_steps=2, warmup=1, fractions=(0.5,), frame_source=_Frames())
    assert r["batch_size"] == 5 and r["steps_timed"] == 2 and r["controller"] == "div_p"
    assert set(r["ms"]) == {"render", "emulate", "estimate", "control_dynamics"}
    assert all(v >= 0 and math.isfinite(v) for v in r["ms"].values())
    assert r["ms_total"] == pytest.approx(sum(r["ms"].values()))
    if estimator == "oracle":  # needs no events: no render, no emulation
        assert r["ms"]["render"] == 0 and r["ms"]["emulate"] == 0 and not r["needs_events"]
    else:
        assert r["ms"]["render"] > 0 and r["events_per_step"] > 0


@pytest.mark.parametrize("controller", ["div_p", "tau_p"])
def test_time_stages_runs_the_loop_with_the_configured_controller(controller, monkeypatch):
    """time_stages flies loop_step (its stage timer) with the controller named by controller.name."""
    import dvsland.sim as sim

    cfg = load_config(None, ["camera.width_px=32", "camera.height_px=32", "estimator.dpr.n_min=3",
                             f"controller.name={controller}"])
    calls = []
    real = sim.loop_step

    def spy(stages, state, thrust=None, timer=None, donate=False):
        calls.append((type(stages.controller).controller_name, thrust is None, timer is not None))
        return real(stages, state, thrust=thrust, timer=timer, donate=donate)

    monkeypatch.setattr(sim, "loop_step", spy)
    r = time_stages(cfg, 3, "cpu", "dpr", n_steps=2, warmup=1, fractions=(0.2, 0.6), frame_source=_Frames())
    assert r["controller"] == controller and r["steps_timed"] == 4
    assert calls and all(c == (controller, True, True) for c in calls)  # closed loop, timed by the loop
    assert r["ms"]["control_dynamics"] > 0


def test_time_stages_bad_input():
    cfg = _small_cfg()
    with pytest.raises(ValueError, match="batch_size"):
        time_stages(cfg, 0, frame_source=_Frames())
    with pytest.raises(ValueError, match="fractions"):
        time_stages(cfg, 2, fractions=(1.5,), frame_source=_Frames())


def test_report_folder_and_docs(tmp_path, monkeypatch):
    """A small real run (oracle presets only, one closed-loop estimator): the three files, machine
    facts, the docs page; nothing left outside the run folder."""
    import tempfile

    from dvsland.bench import run_bench

    private_tmp = tmp_path / "tmp"
    private_tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(private_tmp))  # other processes share /tmp
    out, docs = tmp_path / "bench", tmp_path / "docs"
    rep = run_bench(["tradeoff", "closed_loop"], quick=True, out=out, docs=docs, estimators=["oracle"],
                    closed_loop_estimators=["oracle[noise_rel=0.1]"], log=lambda *a: None)
    assert rep["status"] == "complete"
    for name in ("bench.json", "bench.md", "pareto.png", "config.yaml"):
        assert (out / name).is_file(), name
    data = json.loads((out / "bench.json").read_text())
    m = data["machine"]
    for key in ("cpu_model", "torch_version", "device", "torch_threads", "git_commit", "load_average"):
        assert key in m
    rows = data["tradeoff"]["rows"]
    assert [r["label"] for r in rows] == ["oracle", "oracle[noise_rel=0.1]", "oracle[noise_rel=0.3]"]
    assert rows[0]["error"]["median_abs_rel_err"] < 1e-6 and rows[0]["error"]["coverage"] == 1.0
    assert 0.03 < rows[1]["error"]["median_abs_rel_err"] < 0.12  # 10 % Gaussian noise: median |e| ~ 6.7 %
    cl = data["closed_loop"]["rows"][0]
    assert cl["n"] == 18 and 0 <= cl["wilson95"][0] <= cl["success_rate"] <= cl["wilson95"][1] <= 1
    md = (out / "bench.md").read_text()
    assert "| oracle[noise_rel=0.1] |" in md and "Wilson" in md
    page = (docs / "benchmarks.md").read_text()
    assert "dvsland bench" in page and "benchmarks_pareto.png" in page and (docs / "benchmarks_pareto.png").is_file()
    assert list(private_tmp.iterdir()) == []  # no temporary folder left behind


def test_cli(tmp_path, capsys):
    args = build_parser().parse_args(["bench", "--quick", "--device", "cpu", "--out", str(tmp_path / "b")])
    assert args.what == [] and args.quick and args.device == "cpu"
    assert main(["bench", "nope", "--out", str(tmp_path / "c")]) == 2
    assert "unknown benchmark 'nope'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "--device", "tpu"])


def test_scripts_are_thin_wrappers(repo_root):
    for name in ("bench_render", "bench_events", "bench_v2e", "bench_estimators", "compare_renderers",
                 "profile_sim"):
        text = (repo_root / "scripts" / f"{name}.py").read_text()
        assert "from dvsland.bench." in text and len(text.splitlines()) < 20, name


def test_every_variant_and_closed_loop_spec_builds():
    """The knobs the report varies are accepted by the registered estimators (a typo or a renamed
    estimator would otherwise fail only inside a long run)."""
    from dvsland.bench.run import CLOSED_LOOP_FULL, CLOSED_LOOP_QUICK
    from dvsland.bench.stages import build_estimator
    from dvsland.bench.tradeoff import VARIANTS_FULL, VARIANTS_QUICK

    cfg = load_config(None)
    specs = {s for v in (*VARIANTS_FULL.values(), *VARIANTS_QUICK.values()) for s in v}
    specs |= set(CLOSED_LOOP_FULL) | set(CLOSED_LOOP_QUICK)
    for spec in sorted(specs):
        est = build_estimator(cfg, spec, 2, "cpu")
        assert est.batch_size == 2, spec


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_cli_device_checked_before_any_folder(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["bench", "--device", "cuda", "--out", str(out), "tradeoff"]) == 2
    assert "--device='cuda'" in capsys.readouterr().err
    assert not out.exists()


def test_cli_help_has_a_description(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    assert "speed" in capsys.readouterr().out.split("positional arguments")[0]


def test_scaling_figure_axes_and_legends(tmp_path, monkeypatch):
    """Two batch sizes: the memory axis is linear with plain ticks, both batch axes are ticked at
    the measured B in plain numbers, and every legend entry draws a marker or line."""
    import matplotlib.pyplot as plt

    from dvsland.bench.report import plot_scaling

    rows = [{"batch_size": b, "device": "cpu", "cpu_ms": {"render": 3.0 * b, "emulate": 0.5 * b, "estimate": 1.2 * b,
                                                           "control_dynamics": 0.0},
             "cpu_ms_total": 4.7 * b, "ms_total": 6.0 * b, "peak_memory_mib": m} for b, m in ((1, 412.0), (8, 455.0))]
    seen = {}
    monkeypatch.setattr(plt, "close", lambda fig: seen.setdefault("fig", fig))
    plot_scaling(rows, tmp_path / "scaling.png", "estimator dpr (test)")
    assert (tmp_path / "scaling.png").stat().st_size > 1000
    a1, a2 = seen["fig"].axes
    assert a2.get_yscale() == "linear"
    for ax in (a1, a2):
        assert list(ax.get_xticks()) == [1, 8]
        assert [t.get_text() for t in ax.get_xticklabels()] == ["1", "8"]
        leg = ax.get_legend()
        assert leg is not None
        for h in leg.legend_handles:
            assert h.get_marker() not in (None, "", "None") and h.get_visible()
