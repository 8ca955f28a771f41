"""``simulation.compile``: the filter and the law through ``torch.compile`` fly the same descents
as the eager path (the reference) within float rounding. Compiling takes tens of seconds on this
CPU, so the flight test is slow; the wiring test is not."""

from __future__ import annotations

import pytest
import torch

from dvsland.config import load_config
from dvsland.sim import init_state, loop_step
from dvsland.sim.contracts import CompiledStage, stage_fns
from dvsland.stages import build_stages


def _stages(compile_: bool, n_seeds: int = 2):
    cfg = load_config("montecarlo_efference", ["estimator.name=oracle", f"simulation.compile={str(compile_).lower()}",
                                               f"simulation.n_seeds={n_seeds}"])
    return build_stages(cfg, "D,E")


def test_compile_wraps_only_the_filter_and_the_law():
    fns = stage_fns(_stages(True))
    assert isinstance(fns.filter, CompiledStage) and isinstance(fns.controller, CompiledStage)
    assert not isinstance(fns.estimator, CompiledStage)
    assert callable(fns.filter.init_state) and fns.filter.stage is not None  # the rest delegates
    assert not isinstance(stage_fns(_stages(False)).filter, CompiledStage)


@pytest.mark.slow
def test_compiled_loop_flies_the_eager_descents():
    runs = []
    for compile_ in (False, True):
        stages = _stages(compile_)
        state = init_state(stages)
        zs = []
        for _ in range(40):
            state, out = loop_step(stages, state)
            zs.append(out.z_m)
        runs.append((torch.stack(zs), state))
    torch.testing.assert_close(runs[1][0], runs[0][0], rtol=1e-9, atol=1e-9)
    assert torch.equal(runs[1][1].active, runs[0][1].active)
