"""``python -m dvsland.events.build_native``: compile the emulator's kernels once (see
:mod:`dvsland.events.native`); afterwards every process uses them (mode auto) without compiling.

Prints whether they were already cached, the wall and CPU time (the compiler's CPU included) and
the folder; exit status 1 (and the error) when they cannot be built.
"""

from __future__ import annotations

import resource
import sys
import time


def main(argv=None) -> int:
    from dvsland.events import native

    was = native.cached()
    w0 = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        native.build()
    except Exception as exc:
        print(f"could not build the compiled kernels: {exc}", file=sys.stderr)
        return 1
    r1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum(b.ru_utime + b.ru_stime - a.ru_utime - a.ru_stime for a, b in zip(r0, r1))
    print(f"dvsland.events.native: {'already cached' if was else 'built'} in {time.perf_counter() - w0:.1f} s wall, "
          f"{cpu:.1f} s CPU (compiler included): {native.build_dir()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
