"""``python -m dvsland.events.build_native``: compile the emulator's kernels now (see
:mod:`dvsland.events.native`; otherwise they are built on first use where a C++ compiler is found).
``dvsland build-native`` builds these and ``cmax``'s. Prints whether they were already cached,
the wall and CPU time and the folder; exit status 1 (and the error) when they cannot be built.
"""

from __future__ import annotations

import sys


def main(argv=None) -> int:
    from dvsland.events import native as kernel
    from dvsland.native_build import timed_build

    return timed_build("the emulator kernels", kernel.LIBRARY)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
