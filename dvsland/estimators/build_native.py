"""``python -m dvsland.estimators.build_native``: compile ``cmax``'s splat kernel once (see
:mod:`dvsland.estimators.native_cmax`); afterwards every process uses it (mode auto) without
compiling.

Prints whether it was already cached, the wall and CPU time (the compiler's CPU included) and the
folder; exit status 1 (and the error) when it cannot be built.
"""

from __future__ import annotations

import resource
import sys
import time


def main(argv=None) -> int:
    from dvsland.estimators import native_cmax

    was = native_cmax.cached()
    w0 = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    try:
        native_cmax.build()
    except Exception as exc:
        print(f"could not build the compiled cmax kernel: {exc}", file=sys.stderr)
        return 1
    r1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum(b.ru_utime + b.ru_stime - a.ru_utime - a.ru_stime for a, b in zip(r0, r1))
    print(f"dvsland.estimators.native_cmax: {'already cached' if was else 'built'} in "
          f"{time.perf_counter() - w0:.1f} s wall, {cpu:.1f} s CPU (compiler included): {native_cmax.build_dir()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
