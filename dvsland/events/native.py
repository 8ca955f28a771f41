"""Optional compiled kernel of the emulator: an LSD radix sort of its int64 event keys (CPU).

The emulator's per-step sort of packed event keys (:class:`dvsland.events.emulator._KeyLayout`)
is about half of a dense step with numpy's sort (158 k keys, B = 18 at 128x128, 0.6 events per
pixel: about 6.5 ms of process CPU on this machine against 1.1 ms for this radix sort). Sorting
integers has one result, so the events are identical with and without it (tests pin it).

It is opt-in because it is compiled on first use with the C++ compiler through
``torch.utils.cpp_extension.load_inline`` (about 80 s once on a busy 2-core machine, then cached
in torch's extension folder): set the environment variable ``DVSLAND_NATIVE_SORT=1`` or call
:func:`use_native_sort`. Without a compiler (or on any build error) the numpy sort is used, with
one warning.
"""

from __future__ import annotations

import os
import warnings
from typing import Optional

import torch

_SRC = r"""
#include <torch/extension.h>
#include <cstring>
#include <vector>

// LSD radix sort of non-negative int64 keys below 2^bits, in place; 11-bit digits.
void radix_sort_(torch::Tensor keys, int64_t bits) {
  TORCH_CHECK(keys.is_contiguous() && keys.scalar_type() == torch::kInt64 && keys.device().is_cpu(),
              "radix_sort_: keys must be a contiguous int64 CPU tensor");
  const int64_t n = keys.numel();
  if (n < 2) return;
  int64_t* a = keys.data_ptr<int64_t>();
  std::vector<int64_t> buf(n);
  int64_t* src = a;
  int64_t* dst = buf.data();
  const int D = 11;
  const int64_t M = (int64_t(1) << D) - 1;
  std::vector<int64_t> cnt(size_t(1) << D);
  for (int64_t sh = 0; sh < bits; sh += D) {
    std::fill(cnt.begin(), cnt.end(), 0);
    for (int64_t i = 0; i < n; ++i) cnt[(src[i] >> sh) & M]++;
    if (cnt[(src[0] >> sh) & M] == n) continue;  // one digit value: this pass changes nothing
    int64_t s = 0;
    for (auto& c : cnt) { int64_t t = c; c = s; s += t; }
    for (int64_t i = 0; i < n; ++i) dst[cnt[(src[i] >> sh) & M]++] = src[i];
    std::swap(src, dst);
  }
  if (src != a) std::memcpy(a, src, size_t(n) * sizeof(int64_t));
}
"""

_module = None
_failed = False
_enabled: Optional[bool] = None


def use_native_sort(on: bool = True) -> None:
    """Switch the compiled sort on or off for this process (default: ``DVSLAND_NATIVE_SORT``)."""
    global _enabled
    _enabled = bool(on)


def native_sort_enabled() -> bool:
    """Whether the emulator should try the compiled sort."""
    if _enabled is not None:
        return _enabled
    return os.environ.get("DVSLAND_NATIVE_SORT", "0") not in ("", "0", "false", "no")


def load():
    """The compiled module (built on first call), or None when it cannot be built."""
    global _module, _failed
    if _module is not None or _failed:
        return _module
    try:
        from torch.utils.cpp_extension import load_inline

        _module = load_inline("dvsland_events_native", cpp_sources=_SRC, functions=["radix_sort_"],
                              extra_cflags=["-O3"], verbose=False)
    except Exception as exc:  # no compiler, no headers, ...: the numpy sort stays
        _failed = True
        warnings.warn(f"dvsland.events.native: the compiled sort could not be built ({exc}); "
                      f"using numpy's sort", RuntimeWarning)
    return _module


def radix_sort_(keys: torch.Tensor, bits: int) -> bool:
    """Sort ``keys`` ((N,) int64 CPU, contiguous, values in [0, 2^bits)) in place with the compiled
    kernel; returns False (nothing done) when it is not enabled or not available."""
    if not native_sort_enabled():
        return False
    mod = load()
    if mod is None:
        return False
    mod.radix_sort_(keys, int(bits))
    return True


__all__ = ["use_native_sort", "native_sort_enabled", "load", "radix_sort_"]
