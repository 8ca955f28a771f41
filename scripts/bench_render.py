#!/usr/bin/env python
"""Benchmark of the fast renderer: preparation, throughput, flicker.

A thin wrapper: the code is :mod:`dvsland.bench.stage_render` (also run by ``dvsland bench``).
``python scripts/bench_render.py --help`` lists the options.
"""

import sys

from dvsland.bench.stage_render import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
