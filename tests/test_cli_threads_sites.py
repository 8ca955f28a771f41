"""One command line: ``--threads N`` and ``--sites`` on every command that computes, one parser
each (dvsland.cli.common), checked before any run folder is made; ``bench --set``; the fast
renderer leaves torch's thread count alone unless threads were asked for."""

from __future__ import annotations

import os

import pytest
import torch

from dvsland.cli import common
from dvsland.cli.main import build_parser, main
from dvsland.config import RenderConfig, configs_dir, load_config

COMPUTING = ("simulate", "campaign", "evaluate", "bench", "events", "render")


# ------------------------------------------------------------------ threads
class TestThreads:
    @pytest.mark.parametrize("cmd", COMPUTING)
    def test_smoke_every_command_takes_threads(self, cmd):
        args = build_parser().parse_args([cmd, "--threads", "2"])
        assert args.threads == 2

    @pytest.mark.parametrize("cmd", COMPUTING)
    @pytest.mark.parametrize("bad", ["0", "-1", "x", str(4 * (os.cpu_count() or 1) + 1)])
    def test_out_of_range_is_refused_naming_flag_and_range(self, cmd, bad, capsys):
        with pytest.raises(SystemExit) as exc:
            build_parser().parse_args([cmd, "--threads", bad])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert "--threads" in err and f"from 1 to {common.max_threads()}" in err

    def test_parse_threads(self):
        assert common.parse_threads("3") == 3
        with pytest.raises(ValueError, match=r"--threads must be an integer from 1 to \d+"):
            common.parse_threads(0)

    def test_threads_set_torch_and_renderer_and_win_over_set(self):
        args = build_parser().parse_args(["simulate", "--threads", "2", "--set", "simulation.torch_threads=5",
                                          "--set", "render.threads=0"])
        cfg = common.config_from_args(args)
        assert cfg.simulation.torch_threads == 2 and cfg.render.threads == 2
        cfg = common.config_from_args(build_parser().parse_args(["simulate"]))
        assert cfg.simulation.torch_threads == 1 and cfg.render.threads == 1

    def test_default_is_one_thread_in_schema_and_every_shipped_preset(self):
        assert RenderConfig().threads == 1
        for path in sorted(configs_dir().glob("*.yaml")):
            cfg = load_config(path)
            assert cfg.render.threads == 1 and cfg.simulation.torch_threads == 1, path.name

    def test_apply_threads(self):
        before = torch.get_num_threads()
        try:
            cfg = load_config("paper", ["simulation.torch_threads=2"])
            assert common.apply_threads(cfg) == 2
        finally:
            torch.set_num_threads(before)


class TestRendererLeavesThreadsAlone:
    CAM = None

    @pytest.fixture
    def calls(self, monkeypatch):
        seen = []
        real = torch.set_num_threads

        def spy(n):
            seen.append(n)
            real(n)

        monkeypatch.setattr(torch, "set_num_threads", spy)
        return seen

    def _renderer(self, **kw):
        from dvsland.config import CameraConfig
        from dvsland.render import get_renderer

        return get_renderer("fast", ["A"], CameraConfig(width_px=16, height_px=16), disk_cache=False, **kw)

    def test_one_thread_never_touches_torch(self, calls):
        r = self._renderer(render=RenderConfig(threads=1))
        calls.clear()
        before = torch.get_num_threads()
        torch.set_num_threads(2)  # a caller's own setting (recorded by the spy, then cleared)
        calls.clear()
        try:
            r.render(torch.tensor([500.0, 300.0]), torch.zeros(2, dtype=torch.int64))
            assert calls == [] and torch.get_num_threads() == 2
        finally:
            torch.set_num_threads(before)

    def test_explicit_threads_switch_inside_the_call_and_restore(self, calls):
        r = self._renderer(threads=2)
        calls.clear()
        before = torch.get_num_threads()
        r.render(torch.tensor([500.0, 300.0]), torch.zeros(2, dtype=torch.int64))
        assert torch.get_num_threads() == before
        if before != 2:
            assert calls == [2, before]


# ------------------------------------------------------------------ sites
class TestParseSites:
    def test_names_and_variants(self):
        assert common.parse_sites(" A, E,H~2 ") == ["A", "E", "H~2"]
        assert common.parse_sites(None) is None

    @pytest.mark.parametrize("text,needle", [("Z", "unknown site 'Z'"), ("A~0", "unknown site 'A~0'"),
                                             ("", "at least one site"), ("A,A", "A named twice"),
                                             ("a", "unknown site 'a'")])
    def test_refused(self, text, needle):
        with pytest.raises(ValueError, match="--sites") as exc:
            common.parse_sites(text)
        assert needle in str(exc.value)

    def test_configured_only_for_flown_commands(self):
        cfg = load_config("paper")
        common.check_configured_sites(cfg, ["A", "I"])
        with pytest.raises(ValueError, match="terrain variant"):
            common.check_configured_sites(cfg, ["A~1"])
        cfg2 = common.restrict_sites(load_config("paper"), ["I", "D"])
        assert [s.name for s in cfg2.simulation.sites] == ["D", "I"]


BAD_SITE = {
    "simulate": ["simulate", "--sites", "Q"],
    "simulate-variant": ["simulate", "--sites", "A~1"],
    "campaign": ["campaign", "--sites", "Q", "--n-seeds", "1"],
    "evaluate": ["evaluate", "--sites", "Q", "--estimators", "oracle"],
    "render": ["render", "--sites", "A,Q", "--altitudes", "100"],
    "render-mesh": ["render", "--sites", "A", "--altitudes", "100", "--export-mesh", "Q:200"],
    "events": ["events", "--sites", "Q"],
    "events-site": ["events", "--site", "Q"],
    "bench": ["bench", "economies", "--sites", "Q"],
    "bench-variant": ["bench", "economies", "--sites", "A~2"],
}


@pytest.mark.parametrize("key", sorted(BAD_SITE))
def test_bad_site_refused_before_any_folder(tmp_path, capsys, key):
    out = tmp_path / "run"
    rc = main([*BAD_SITE[key], "--out", str(out), "--set", f"logging.root={tmp_path / 'logs'}"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "site" in err and ("Q" in err or "~" in err)
    assert not out.exists() and not (tmp_path / "logs").exists()


def test_campaign_sites_restrict_the_plan(monkeypatch, tmp_path):
    import dvsland.campaign as campaign_pkg

    seen = {}

    class Done:
        status = "complete"

    def fake_run_campaign(cfg, **kw):
        seen["cfg"] = cfg
        return Done()

    monkeypatch.setattr(campaign_pkg, "run_campaign", fake_run_campaign)
    assert main(["campaign", "--sites", "H,D", "--threads", "2", "--out", str(tmp_path / "c")]) == 0
    cfg = seen["cfg"]
    assert [s.name for s in cfg.simulation.sites] == ["D", "H"]
    assert cfg.simulation.torch_threads == 2 and cfg.render.threads == 2


def test_bench_set_and_sites(monkeypatch, tmp_path):
    import dvsland.bench.run as bench_run

    seen = {}
    monkeypatch.setattr(bench_run, "_part_economies", lambda report, cfg, quick, log: seen.update(cfg=cfg))
    out = tmp_path / "b"
    assert main(["bench", "economies", "--sites", "D,E", "--set", "emulator.threshold=0.2", "--out", str(out),
                 "--quiet"]) == 0
    cfg = seen["cfg"]
    assert [s.name for s in cfg.simulation.sites] == ["D", "E"] and cfg.emulator.threshold == 0.2
    assert "Sites D, E; overrides: emulator.threshold=0.2" in (out / "bench.md").read_text()


def test_bench_bad_set_refused_before_folder(tmp_path, capsys):
    out = tmp_path / "b"
    assert main(["bench", "economies", "--set", "emulator.bogus=1", "--out", str(out)]) == 2
    assert "bogus" in capsys.readouterr().err and not out.exists()
