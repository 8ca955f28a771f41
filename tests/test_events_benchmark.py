"""The emulator benchmark (dvsland.events.benchmark): runs, reports, and compares against v2e when
its emulator is present in bench_env/v2e (git-ignored; see docs/events.md)."""

from pathlib import Path

import pytest
import torch

from dvsland.events.benchmark import bench_noise, bench_vs_v2e, format_results, load_v2e

V2E_DIR = Path(__file__).resolve().parents[1] / "bench_env" / "v2e"


def _frames(n=5, B=2, H=16, W=24):
    g = torch.Generator().manual_seed(0)
    base = torch.rand(B, H, W, generator=g) + 0.05
    return torch.stack([base * torch.exp(0.3 * k * torch.randn(B, H, W, generator=g)) for k in range(n)])


def test_bench_without_v2e_reports_why(tmp_path):
    res = bench_vs_v2e(_frames(), v2e_dir=tmp_path / "nowhere", threads=None)
    assert res["v2e"] is None and "FileNotFoundError" in res["v2e_error"]
    for k in ("dvsland_per_stream", "dvsland_batched"):
        assert res[k]["cpu_ms_per_frame"] >= 0 and res[k]["events_per_frame"] > 0
    # per-stream and batched emulate the same events
    assert res["dvsland_per_stream"]["events_per_frame"] == res["dvsland_batched"]["events_per_frame"]
    txt = format_results(res, bench_noise(_frames(), threads=None))
    assert "not run" in txt and "shot_noise_rate_hz" in txt
    with pytest.raises(ValueError, match="frames"):
        bench_vs_v2e(_frames(n=2), threads=None)
    with pytest.raises(FileNotFoundError, match="emulator.py"):
        load_v2e(tmp_path)


@pytest.mark.skipif(not (V2E_DIR / "v2ecore" / "emulator.py").is_file(), reason="v2e not copied into bench_env/v2e")
def test_bench_against_v2e():
    res = bench_vs_v2e(_frames(n=4, B=1, H=32, W=32), v2e_dir=V2E_DIR, threads=None)
    assert res["v2e"] is not None and res["v2e"]["events_per_frame"] > 0
    assert res["dvsland_per_stream"]["speedup_vs_v2e"] > 0
