"""The loop keeps no state in its stage objects: flying ``loop_step`` changes no attribute of the
emulator, the estimator, the filter or the law (every buffer and counter lives in the LoopState),
for every shipped estimator. The counted attributes are the figure the stage contract aims at: 0."""

from __future__ import annotations

import copy
import dataclasses
import types

import pytest
import torch

from dvsland.config import load_config
from dvsland.sim import init_state, loop_step
from dvsland.stages import build_stages

pytestmark = pytest.mark.usefixtures("one_thread")


def _fingerprint(obj) -> dict:
    """A deep copy of ``obj``'s attributes (torch modules by their parameters' values)."""
    out = {}
    for k, v in vars(obj).items():
        if isinstance(v, torch.nn.Module):
            out[k] = [p.detach().clone() for p in v.state_dict().values()]
        else:
            try:
                out[k] = copy.deepcopy(v)
            except Exception:  # noqa: BLE001 - something that cannot be copied is compared by identity
                out[k] = v
    return out


def _same(a, b, depth: int = 0) -> bool:
    if depth > 6:
        return True
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor) and a.shape == b.shape and \
            a.dtype == b.dtype and torch.equal(a.nan_to_num(-7.0), b.nan_to_num(-7.0))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y, depth + 1) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k], depth + 1) for k in a)
    if isinstance(a, torch.nn.Module) and isinstance(b, torch.nn.Module):  # weights
        return _same(list(a.state_dict().values()), list(b.state_dict().values()), depth + 1)
    if type(a) is type(b) and hasattr(a, "__dict__") and not isinstance(a, (types.FunctionType, types.MethodType)):
        return _same(vars(a), vars(b), depth + 1)  # a settings record or a helper object
    if dataclasses.is_dataclass(a) and type(a) is type(b):
        return all(_same(getattr(a, f.name), getattr(b, f.name), depth + 1) for f in dataclasses.fields(a))
    try:
        eq = a == b
        return bool(eq) if not isinstance(eq, torch.Tensor) else bool(eq.all())
    except Exception:  # noqa: BLE001
        return a is b


def changed_attributes(stages, n_steps: int = 6) -> dict:
    """{stage: [attributes that ``n_steps`` of loop_step changed]} of the four stateful stages."""
    objs = {"emulator": stages.emulator, "estimator": stages.estimator, "filter": stages.filter,
            "controller": stages.controller}
    state = init_state(stages)
    before = {k: _fingerprint(o) for k, o in objs.items() if o is not None}
    for _ in range(n_steps):
        state, _ = loop_step(stages, state)
    after = {k: _fingerprint(o) for k, o in objs.items() if o is not None}
    return {k: sorted(a for a in after[k].keys() | before[k].keys()
                      if a not in before[k] or a not in after[k] or not _same(before[k][a], after[k][a]))
            for k in after}


@pytest.mark.parametrize("preset,est", [("paper", "oracle"), ("paper", "dpr"), ("paper", "cmax"), ("paper", "snn"),
                                        ("paper", "learned"), ("montecarlo_efference", "cmax")])
def test_loop_step_changes_no_stage_attribute(preset, est):
    over = [f"estimator.name={est}", "render.threads=1", "camera.width_px=64", "camera.height_px=64"]
    if "montecarlo" in preset:
        over.append("simulation.n_seeds=1")
    if est in ("snn", "learned"):  # their shipped checkpoints are for the 128 x 128 sensor
        over = over[:2]
    stages = build_stages(load_config(preset, over), "D")
    assert changed_attributes(stages) == {k: [] for k in changed_attributes(stages)}


def _outputs(out) -> list:
    return [out.d_est, out.thrust_n, out.z_m, out.v_mps] + ([out.events.t, out.events.x] if out.events else [])


@pytest.mark.parametrize("est,compiled", [("dpr", True), ("cmax", True), ("dpr", False)])
def test_donated_steps_give_the_pure_steps_outputs(est, compiled, monkeypatch):
    """loop_step(donate=True) moves the emulator's pixel buffers in place: the same outputs and next
    states as the pure step, and the pure step leaves its input state as it was; with the compiled
    pixel kernel and with the emulator's torch path (a GPU's)."""
    from dvsland.events import native
    from dvsland.pytree import tree_clone, tree_equal

    monkeypatch.setattr(native.LIBRARY, "chosen", compiled)

    over = [f"estimator.name={est}", "render.threads=1", "camera.width_px=64", "camera.height_px=64"]
    stages = build_stages(load_config("paper", over), "D")
    pure = init_state(stages)
    donated, n_events = tree_clone(pure), 0
    for _ in range(8):
        before = tree_clone(pure)
        pure_next, out_p = loop_step(stages, pure)
        assert tree_equal(before, pure)
        pure = pure_next
        donated, out_d = loop_step(stages, donated, donate=True)
        assert all(_same(a, b) for a, b in zip(_outputs(out_p), _outputs(out_d)))
        assert tree_equal(pure, donated)
        n_events += len(out_p.events) if out_p.events is not None else 0
    assert n_events > 0


def test_closed_loop_reads_a_given_state_and_donates_its_own():
    from dvsland.pytree import tree_clone, tree_equal
    from dvsland.sim import ClosedLoop

    over = ["estimator.name=dpr", "render.threads=1", "camera.width_px=64", "camera.height_px=64"]
    stages = build_stages(load_config("paper", over), "D")
    given = init_state(stages)
    loop = ClosedLoop(stages, given)
    loop.step()  # steps the given state: builds the emulator's state from the first frame
    kept = tree_clone(loop.state)
    loop.step()  # the loop's own state: donated
    loop.step()
    assert not tree_equal(kept, loop.state)
    ref = ClosedLoop(stages, kept)  # from a copy: the same as going on, and the copy unchanged
    copy_of_kept = tree_clone(kept)
    ref.step()
    ref.step()
    assert tree_equal(kept, copy_of_kept) and tree_equal(ref.state, loop.state)
