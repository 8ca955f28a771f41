"""``torch.compile`` for the loop's pure tensor functions, with an eager fallback.

Three settings use it: ``simulation.compile`` (the filter's and the law's steps, wrapped by
:class:`dvsland.sim.contracts.CompiledStage`), ``render.compile`` (the fast renderer's sampling on its
torch path, :class:`dvsland.render.fast.FastRenderer`) and ``emulator.compile`` (the ideal pixel's step
over every pixel, :mod:`dvsland.events.emulator_dense`). Each is "auto", "true" or "false";
:func:`compile_on` resolves them: auto means a CUDA device, where fusing many small elementwise
kernels into a few pays; on a CPU the compiled C++ kernels already do that work, and inductor would
need a C++ compiler and tens of seconds.

:class:`CompiledFn` traces with every size symbolic (``dynamic=True``), so a new batch size or a
history that grows reuses the traced function instead of recompiling it up to torch's limit. Where
compiling fails (no working Triton or C++ compiler, say), the call runs eagerly, warns once naming the
setting, and stays eager; an error of the function itself is raised exactly as the eager call raises it.
"""

from __future__ import annotations

import warnings
from typing import Any, Callable, Optional

#: torch.compile's backend ("inductor": fused kernels; tests use "eager", which traces without code generation)
BACKEND = "inductor"

#: the words of a compile setting
MODES = ("auto", "true", "false")


def compile_on(mode: Any, device: Any) -> bool:
    """Whether a compile setting ``mode`` ("auto", "true", "false"; a bool too) compiles on ``device`` (a
    torch.device or its name): "auto" on a CUDA device only."""
    word = str(mode).lower()
    if word != "auto":
        return word == "true"
    return str(device).split(":")[0] == "cuda"


class CompiledFn:
    """``fn`` through ``torch.compile(dynamic=True)``, falling back to ``fn`` itself (module doc).

    Args:
        fn: a function of tensors.
        setting: the config key that asked for it, named in the fallback's warning.
        label: what ``fn`` is, for the warning.
        backend: torch.compile's backend (default :data:`BACKEND`).
    """

    def __init__(self, fn: Callable, setting: str, label: str, backend: Optional[str] = None):
        import torch

        self.fn, self.setting, self.label = fn, setting, label
        self._compiled = torch.compile(fn, dynamic=True, backend=backend or BACKEND)
        self.eager = False  # True once compiling failed: every later call runs fn

    def __call__(self, *args, **kwargs):
        if self.eager:
            return self.fn(*args, **kwargs)
        try:
            return self._compiled(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - the eager call below tells a compiler's failure from fn's
            out = self.fn(*args, **kwargs)  # fn's own error raises here, as eager
            self.eager = True
            warnings.warn(f"{self.setting}: torch.compile failed for {self.label} ({type(exc).__name__}: "
                          f"{str(exc)[:300]}); it runs eagerly ({self.setting}=false avoids the attempt)",
                          RuntimeWarning, stacklevel=2)
            return out


__all__ = ["BACKEND", "MODES", "CompiledFn", "compile_on"]
