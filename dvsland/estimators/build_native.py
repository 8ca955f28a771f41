"""``python -m dvsland.estimators.build_native``: compile ``cmax``'s splat kernel now (see
:mod:`dvsland.estimators.native_cmax`; otherwise it is built on first use where a C++ compiler is
found). ``dvsland build-native`` builds this and the emulator's. Prints whether it was already
cached, the wall and CPU time and the folder; exit status 1 (and the error) when it cannot be built.
"""

from __future__ import annotations

import sys


def main(argv=None) -> int:
    from dvsland.estimators import native_cmax as kernel
    from dvsland.native_build import timed_build

    return timed_build("the cmax kernel", kernel.LIBRARY)


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
