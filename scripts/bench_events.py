#!/usr/bin/env python
"""Benchmark of the event emulator: time per step, events/s, burst memory.

A thin wrapper: the code is :mod:`dvsland.bench.stage_events` (also run by ``dvsland bench``).
``python scripts/bench_events.py --help`` lists the options.
"""

import sys

from dvsland.bench.stage_events import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
