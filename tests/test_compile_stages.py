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


@pytest.mark.parametrize("value, device, on", [
    ("auto", "cpu", False), ("auto", "cuda", True), ("auto", "cuda:1", True),
    ("true", "cpu", True), ("false", "cuda", False), ("off", "cuda", False), ("yes", "cpu", True),
])
def test_auto_compiles_on_a_gpu_only(value, device, on):
    from dvsland.stages import LoopSettings

    cfg = load_config("montecarlo_efference", [f"simulation.compile={value}"])  # YAML reads off/yes as booleans
    assert cfg.simulation.compile in ("auto", "true", "false")
    assert LoopSettings.from_config(cfg, device).compile is on
    cfg.simulation.device = device  # without a device: simulation.device's
    assert LoopSettings.from_config(cfg).compile is on


def test_compile_setting_checked():
    from dvsland.config import ConfigError

    assert load_config("montecarlo_efference").simulation.compile == "auto"
    assert load_config("montecarlo_efference", ["simulation.compile=true"]).simulation.compile == "true"
    with pytest.raises(ConfigError, match=r"simulation\.compile.*'fast'.*'auto', 'true', 'false'"):
        load_config("montecarlo_efference", ["simulation.compile=fast"])


class _Doubler:
    def step_state(self, x, k=1):
        if k < 0:
            raise ValueError("k must be >= 0")
        return 2 * x + k


def test_a_failing_compile_runs_eagerly(failing_compile):
    calls = failing_compile
    st = CompiledStage(_Doubler())
    with pytest.warns(RuntimeWarning, match="torch.compile failed for _Doubler.*no working compiler"):
        assert st.step_state(torch.tensor(3.0), k=1).item() == 7.0
    assert st.step_state(torch.tensor(1.0)).item() == 3.0  # eager from then on: the compiled step is not tried again
    assert len(calls) == 1
    with pytest.raises(ValueError, match="k must be"):  # the step's own error, as the eager step raises it
        CompiledStage(_Doubler()).step_state(torch.tensor(1.0), k=-1)


def test_a_new_batch_size_reuses_the_compiled_step(monkeypatch):
    """Stage sets of other batch sizes (the next batch of a campaign, a bench's next B) and a history that
    grows each step reuse the traced step: no recompile, so torch's recompile limit never turns it eager."""
    from torch._dynamo.utils import counters

    import dvsland.sim.contracts as contracts

    torch._dynamo.reset()
    counters.clear()
    monkeypatch.setattr(contracts, "COMPILE_BACKEND", "eager")  # dynamo's tracing and guards, no code generation
    graphs = []
    for n_seeds in (2, 3, 1):
        stages = _stages(True, n_seeds)
        state = init_state(stages)
        for _ in range(4):
            state, _ = loop_step(stages, state)
        assert state.z_m.shape[0] == 2 * n_seeds
        graphs.append(counters["stats"]["unique_graphs"])
    assert graphs[0] > 0
    assert graphs[1] == graphs[0] and graphs[2] == graphs[0], graphs
