"""The fleet (dvsland.sim.fleet): many descents through B slots that restart as soon as theirs ends.

Short flights (``simulation.t_max_s`` of a few seconds: every descent times out) keep the tests fast;
the oracle needs no rendering, so a restart is compared bit for bit with a new flight."""

from __future__ import annotations

import pytest
import torch

from dvsland.bench.fleet import run_fleet, steady_rate
from dvsland.config import load_config
from dvsland.envs.layout import fit_layout
from dvsland.sim import init_state, loop_step
from dvsland.sim.fleet import FLEET_FIELDS, fleet_rows, fly_fleet, restart_conditions
from dvsland.stages import build_stages

FIX = ["dispersion.terrain_variants=1", 'dispersion.sun_elevation_deg={kind: "off"}', "render.threads=1"]


def _stages(B=3, est="oracle", t_max=3.0, extra=()):
    cfg = load_config("montecarlo_efference", [f"estimator.name={est}", f"simulation.t_max_s={t_max}", *FIX, *extra])
    return build_stages(cfg, fit_layout(cfg, None, B), "cpu")


def _fly_alone(stages, b, restart):
    """Slot b's descent ``restart`` flown from a new state (every slot with that restart's conditions)."""
    st = init_state(stages)
    if restart:
        z, v, seed = restart_conditions(stages, torch.full((stages.batch_size,), restart))
        st = init_state(stages, z_m=z, v_mps=v)._replace(noise_seed=seed)
    while bool(st.active[b]):
        st, _ = loop_step(stages, st)
    return st


def test_smoke_and_shapes():
    stages = _stages()
    r = fly_fleet(stages, 7, check_every=1)
    assert r.complete and r.n_started == 7 and r.n_ended == 7 and r.steps == 3 * 30
    assert set(r.descents) == set(FLEET_FIELDS) and all(v.shape == (7,) for v in r.descents.values())
    assert sorted(r.descents["restart"].tolist()) == [0, 0, 0, 1, 1, 1, 2]
    assert r.outcome_counts() == {"timeout": 7} and r.descents_per_minute() > 0
    rows = fleet_rows(stages, r)
    assert len(rows) == 7 and rows[0]["site"] in ("A", "B", "C") and rows[0]["outcome"] == "timeout"
    assert rows[0]["estimator"] == "oracle" and isinstance(rows[0]["lowest_altitude_m"], float)


@pytest.mark.parametrize("check_every", [1, 4])
def test_every_descent_is_the_same_as_flown_alone(check_every):
    """Restart 0 is the layout's own descent, bit for bit; restart r >= 1 the same as a new flight of
    its conditions, whenever the fleet started it, to rounding (the filter's sums run over the
    batch's longer history; the oracle has no events)."""
    stages = _stages()
    r = fly_fleet(stages, 8, check_every=check_every)
    d = r.descents
    for i in range(r.n_ended):
        b, k = int(d["slot"][i]), int(d["restart"][i])
        alone = _fly_alone(stages, b, k)
        got, want = torch.stack([d["z_end_m"][i], d["v_end_mps"][i]]), torch.stack([alone.z_m[b], alone.v_mps[b]])
        assert torch.equal(got, want) if k == 0 else torch.allclose(got, want, rtol=1e-12, atol=0)
        assert float(alone.t_end_s[b]) == float(d["t_end_s"][i]) and float(alone.z_m[b]) < float(d["z0_m"][i])


def test_restart_conditions_follow_the_dispersion_and_the_slot_only():
    small, big = _stages(B=3), _stages(B=9)
    z3, v3, s3 = restart_conditions(small, torch.tensor([1, 2, 1]))
    z9, v9, s9 = restart_conditions(big, torch.tensor([1, 2, 1] + [5] * 6))
    assert torch.equal(z3, z9[:3]) and torch.equal(v3, v9[:3]) and torch.equal(s3, s9[:3])  # not of B
    assert not torch.equal(z3[0], restart_conditions(small, torch.tensor([2, 2, 2]))[0][0])  # new per restart
    nominal = torch.tensor([s.z0_m for s in small.cfg.simulation.sites if s.name in "ABC"], dtype=torch.float64)
    assert bool(((z3 / nominal > 0.9) & (z3 / nominal < 1.1)).all())  # z0_scale uniform [0.9, 1.1]
    off = _stages(B=3, extra=['dispersion.z0_scale={kind: "off"}'])
    assert torch.allclose(restart_conditions(off, torch.tensor([4, 4, 4]))[0], nominal, rtol=1e-12)
    assert bool((s3 >= 0).all()) and len(set(s9.tolist())) == 9


def test_fewer_descents_than_slots_and_a_step_limit():
    stages = _stages(B=4)
    r = fly_fleet(stages, 2, check_every=1)
    assert r.complete and r.n_ended == 2 and sorted(r.descents["slot"].tolist()) == [0, 1]
    cut = fly_fleet(stages, 50, check_every=2, max_steps=45)
    assert not cut.complete and cut.steps == 45 and cut.n_ended == 4 and cut.n_started == 8


@pytest.mark.parametrize("kw,msg", [(dict(n_descents=0), "n_descents must be an integer in"),
                                    (dict(n_descents=2.0), "n_descents must be"),
                                    (dict(n_descents=3, check_every=0), r"check_every must be an integer in \[1, 1000\]"),
                                    (dict(n_descents=3, max_steps=0), "max_steps must be"),
                                    (dict(n_descents=True), "n_descents must be")])
def test_bad_input_is_named(kw, msg):
    with pytest.raises(ValueError, match=msg):
        fly_fleet(_stages(B=2), **kw)


def test_event_estimator_flies_whole_descents_and_restarts():
    stages = _stages(B=2, est="learned", t_max=1.5)
    r = fly_fleet(stages, 5, check_every=3)
    assert r.complete and r.n_ended == 5 and r.outcome_counts() == {"timeout": 5}
    assert torch.isfinite(r.descents["z_end_m"]).all() and sorted(r.descents["restart"].tolist()) == [0, 0, 1, 1, 2]


def test_bench_row_and_steady_rate():
    runs, row = run_fleet("oracle", 3, 9, "cpu", overrides=["simulation.t_max_s=2.0", *FIX], check_every=1)
    assert len(runs) == 9 and row["landed_by_site"] == {"A": [0, 3], "B": [0, 3], "C": [0, 3]}
    assert row["n_ended"] == 9 and row["complete"] and row["outcomes"] == {"timeout": 9}
    assert row["descents_per_min"] > 0 and row["steady_descents_per_min"] is not None
    assert steady_rate([(0.0, 1, 0, 3), (1.0, 2, 3, 6), (2.0, 3, 6, 9)], 3, 9) == 180.0
    assert steady_rate([(0.0, 1, 0, 3)], 3, 3) is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_fleet_on_cuda_matches_cpu():
    """The same fleet on the GPU: the same descents end in the same slots with the same outcomes."""
    def fleet(dev):
        cfg = load_config("montecarlo_efference", ["estimator.name=learned", "simulation.t_max_s=2.0",
                                                   f"simulation.device={dev}", *FIX])
        return fly_fleet(build_stages(cfg, fit_layout(cfg, None, 4), dev), 10, check_every=2)

    cpu, gpu = fleet("cpu"), fleet("cuda")
    for k in ("slot", "restart", "outcome", "end_step"):
        assert torch.equal(cpu.descents[k], gpu.descents[k]), k
    # the CNN and the float32 passes round differently on the card: the paths agree, not the bits
    assert torch.allclose(cpu.descents["z_end_m"], gpu.descents["z_end_m"], rtol=1e-3)


def test_rows_are_written_as_they_end_and_survive_an_interrupt(tmp_path):
    from dvsland.bench.fleet import RowsCsv

    path, calls = tmp_path / "runs.csv", []

    def write_then_stop(rows):
        calls.append(len(rows))
        out.write(rows)
        if len(calls) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt), RowsCsv(path) as out:
        run_fleet("oracle", 3, 12, "cpu", overrides=["simulation.t_max_s=2.0", *FIX], check_every=1,
                  on_rows=write_then_stop)
    lines = path.read_text().splitlines()
    assert lines[0].startswith("slot,site,scene,label,estimator,restart,outcome") and len(lines) == 1 + sum(calls) == 7
