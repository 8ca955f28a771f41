#!/usr/bin/env python
"""Benchmark of dvsland's emulator against v2e on the same frames, and of the pixel model's cost.

A thin wrapper: the code is :mod:`dvsland.bench.stage_v2e` (also run by ``dvsland bench v2e``).
``python scripts/bench_v2e.py --help`` lists the options.
"""

import sys

from dvsland.bench.stage_v2e import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
