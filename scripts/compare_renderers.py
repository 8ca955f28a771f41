#!/usr/bin/env python
"""Benchmark of the pyrender reference vs fast renderer: timing and agreement.

A thin wrapper: the code is :mod:`dvsland.bench.stage_renderers` (also run by ``dvsland bench``).
``python scripts/compare_renderers.py --help`` lists the options.
"""

import sys

from dvsland.bench.stage_renderers import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
