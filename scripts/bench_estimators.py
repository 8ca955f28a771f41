#!/usr/bin/env python
"""Benchmark of the estimators: time per update (synthetic events), optional open-loop evaluation.

A thin wrapper: the code is :mod:`dvsland.bench.stage_estimators` (also run by ``dvsland bench``).
``python scripts/bench_estimators.py --help`` lists the options.
"""

import sys

from dvsland.bench.stage_estimators import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
