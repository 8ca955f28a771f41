#!/usr/bin/env python
"""Benchmark of the where the closed loop's time goes, per stage.

A thin wrapper: the code is :mod:`dvsland.bench.stage_sim` (also run by ``dvsland bench``).
``python scripts/profile_sim.py --help`` lists the options.
"""

import sys

from dvsland.bench.stage_sim import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
