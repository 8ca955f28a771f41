"""simulate() = build -> run -> write, with callbacks around the loop."""

from __future__ import annotations

import json

import pytest

from dvsland.sim import simulate
from dvsland.sim.callbacks import Callback, CallbackList, default_callbacks

QUIET = ["logging.tensorboard=false", "logging.figures=false", "simulation.t_max_s=3"]


class Recorder(Callback):
    def __init__(self, fail_at=None):
        self.calls, self.fail_at = [], fail_at

    def on_start(self, loop):
        self.calls.append(("start", loop.step_index))

    def on_step(self, loop, out):
        assert out.step == loop.step_index - 1
        self.calls.append(("step", loop.step_index))
        if self.fail_at is not None and loop.step_index == self.fail_at:
            raise RuntimeError("boom")

    def on_end(self, loop, result):
        self.calls.append(("end", result.status))
        result.timings_s["recorder"] = 0.0

    def close(self):
        self.calls.append(("close", None))


def test_callback_hooks_in_order(tmp_path):
    rec = Recorder()
    r = simulate(None, estimator="oracle", sites="D", out=tmp_path / "r", quiet=True, overrides=QUIET,
                 callbacks=[rec])
    assert rec.calls[0] == ("start", 0)
    steps = [k for what, k in rec.calls if what == "step"]
    assert steps == list(range(1, r.n_steps + 1))
    assert rec.calls[-2:] == [("end", "complete"), ("close", None)]
    saved = json.loads((r.run_dir / "results.json").read_text())
    assert "recorder" in saved["timings_s"]  # results.json is rewritten after on_end


def test_failing_callback_still_writes_and_closes(tmp_path):
    rec = Recorder(fail_at=5)
    with pytest.raises(RuntimeError, match="boom"):
        simulate(None, estimator="oracle", sites="D", out=tmp_path / "f", quiet=True, overrides=QUIET,
                 callbacks=[rec])
    assert rec.calls[-2:] == [("end", "interrupted"), ("close", None)]
    saved = json.loads((tmp_path / "f" / "results.json").read_text())
    assert saved["status"] == "interrupted" and saved["n_steps"] == 5
    assert (tmp_path / "f" / "traces.npz").is_file()


def test_default_callbacks_follow_logging_config(tmp_path):
    from dvsland.config import load_config
    from dvsland.sim import ClosedLoop, build_layout
    from dvsland.stages import build_stages

    cfg = load_config("paper", ["estimator.name=oracle", "logging.quiet=true", "logging.tensorboard=false"])
    st = build_stages(cfg, "D")
    loop = ClosedLoop(st)
    names = [type(c).__name__ for c in default_callbacks(cfg, tmp_path, loop)]
    assert names == ["FiguresCallback"]
    cfg.logging.quiet, cfg.logging.tensorboard = False, True
    names = [type(c).__name__ for c in default_callbacks(cfg, tmp_path, loop, on_step=print)]
    assert names == ["TensorBoardCallback", "StepFunction", "ProgressCallback", "FiguresCallback", "SummaryCallback"]
    assert isinstance(build_layout(cfg, ["D"]).batch_size, int)


def test_callback_list_closes_all_then_raises():
    closed = []

    class Bad(Callback):
        def close(self):
            closed.append("bad")
            raise OSError("disk")

    class Good(Callback):
        def close(self):
            closed.append("good")

    with pytest.raises(OSError, match="disk"):
        CallbackList([Bad(), Good(), object()]).close()
    assert closed == ["bad", "good"]
