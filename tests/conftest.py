"""Shared fixtures: devices to test on (CPU always, CUDA when present), repo paths."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]

# One intra-op thread: the tests' tensors are small, and on 2 shared cores torch's default of 2
# threads made small ops 10-400x slower (measured); the simulator's default is 1 thread too.
torch.set_num_threads(1)


#: the CPU the bit-for-bit references of the tests were recorded on: (machine, torch's CPU capability,
#: vendor). Another CPU may round float reductions (convolutions, sums) differently in the last bits:
#: those tests then compare to a tolerance or to that CPU's own recorded variant, as
#: scripts/loop_reference.py does.
RECORDING_CPU = ("x86_64", "AVX512", "GenuineIntel")


def cpu_identity() -> tuple:
    """(machine, torch's CPU capability, vendor id from /proc/cpuinfo or "") of this machine."""
    import platform

    vendor = ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            vendor = next((line.split(":", 1)[1].strip() for line in f if line.startswith("vendor_id")), "")
    except OSError:
        pass
    return platform.machine(), torch.backends.cpu.get_cpu_capability(), vendor


@pytest.fixture(scope="session")
def native_kernels():
    """``native_kernels(library, what)``: the bindings of a compiled library
    (:class:`dvsland.native_build.NativeLibrary`), built here when needed, whatever its mode; the test
    is skipped where they cannot be built (no C++ compiler)."""
    def load(library, what: str):
        k = library.load(force=True)
        if k is None:
            pytest.skip(f"no C++ compiler: {what} cannot be built here")
        return k

    return load


@pytest.fixture(scope="session")
def recording_cpu() -> bool:
    """Whether this CPU is :data:`RECORDING_CPU` (the recorded references hold bit for bit)."""
    return cpu_identity() == RECORDING_CPU


@pytest.fixture(scope="session")
def cpu_vendor() -> str:
    """This CPU's vendor id ("GenuineIntel", "AuthenticAMD", ... or "")."""
    return cpu_identity()[2]


def _devices():
    devs = ["cpu"]
    if torch.cuda.is_available():
        devs.append("cuda")
    return devs


@pytest.fixture(params=_devices())
def device(request) -> torch.device:
    """Every device present: 'cpu', and 'cuda' when available (kornia-style)."""
    return torch.device(request.param)


@pytest.fixture(scope="module")
def torch_event_path():
    """The emulator's and denoiser's torch path for a whole test module, whether or not the compiled
    kernels are built (``pytestmark = pytest.mark.usefixtures("torch_event_path")``)."""
    from dvsland.events import native

    with native.native_sort_mode(False):
        yield


@pytest.fixture
def failing_compile(monkeypatch):
    """``torch.compile`` replaced by a compiler that fails on every call of what it compiled (no working
    Triton or C++ compiler); returns the list each attempt appends to."""
    import torch

    calls = []

    def broken(fn, **options):
        def run(*args, **kwargs):
            calls.append(1)
            raise RuntimeError("no working compiler")
        return run

    monkeypatch.setattr(torch, "compile", broken)
    return calls


@pytest.fixture
def count_calls(monkeypatch):
    """``count_calls(cls, name)`` wraps method ``name`` of ``cls`` for this test (restored after it)
    and returns the list that each call appends to: which path a test ran."""
    def count(cls, name: str) -> list:
        calls, real = [], getattr(cls, name)

        def spy(self, *a, **kw):
            calls.append(1)
            return real(self, *a, **kw)

        monkeypatch.setattr(cls, name, spy)
        return calls

    return count


@pytest.fixture
def repo_root() -> Path:
    return REPO


@pytest.fixture
def paper_yaml() -> Path:
    return REPO / "configs" / "paper.yaml"


# Property and fuzz tests: a fixed example sequence by default, so the default run (and CI) is
# reproducible; set DVSLAND_HYPOTHESIS=explore for fresh random examples on each run.
try:
    import os as _os

    from hypothesis import settings as _hyp_settings

    _hyp_settings.register_profile("dvsland-default", derandomize=True, print_blob=True)
    _hyp_settings.register_profile("explore", derandomize=False, print_blob=True)
    _hyp_settings.load_profile("explore" if _os.environ.get("DVSLAND_HYPOTHESIS") == "explore" else "dvsland-default")
except ImportError:  # hypothesis is a dev dependency; tests that need it import it themselves
    pass


#: source of a tiny import-path estimator (D_hat = D / 2, needs no events), for the tests that load one
HALF_ESTIMATOR_SOURCE = (
    "import torch\n"
    "from dvsland.estimators import DivergenceEstimator\n"
    "class Half(DivergenceEstimator):\n"
    "    needs_events = False\n"
    "    def reset(self, mask=None):\n"
    "        pass\n"
    "    def update(self, events, t_us, truth=None):\n"
    "        return truth.divergence.float() * 0.5 if truth is not None else "
    "torch.full((self.batch_size,), float('nan'))\n")


@pytest.fixture
def half_estimator_source() -> str:
    """:data:`HALF_ESTIMATOR_SOURCE`: write it to a .py file and load ``file.py:Half``."""
    return HALF_ESTIMATOR_SOURCE


class BlindEstimator:
    """An object-API estimator on a scene with no usable events: never an estimate, confidence 0."""

    needs_events = False

    def __init__(self, batch_size):
        self.batch_size = batch_size

    def reset(self, mask=None):
        pass

    def update(self, events, t_us, truth=None):
        return torch.full((self.batch_size,), float("nan"), dtype=torch.float32)

    def confidence(self):
        return torch.zeros(self.batch_size, dtype=torch.float32)


@pytest.fixture
def blind_estimator():
    """:class:`BlindEstimator` (the class: ``blind_estimator(B)`` builds one for B descents)."""
    return BlindEstimator


@pytest.fixture
def one_thread():
    """One torch thread for the test (small tensors on a shared 2-core machine run far faster on
    one), restored after it. Use with ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A dataset folder of `dvsland dataset build`: five one-second descents of site A in one shard
    (montecarlo_efference, one thread), built once per test session; read it, do not write into it."""
    from dvsland.data import build_dataset

    out = tmp_path_factory.mktemp("ds") / "tiny5"
    build_dataset("montecarlo_efference", out=out, n_seeds=5, sites="A", shard_size=5, quiet=True,
                  overrides=["render.threads=1", "simulation.torch_threads=1", "simulation.t_max_s=1.0"])
    return out
