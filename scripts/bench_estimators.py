#!/usr/bin/env python
"""Benchmark of the estimators: time per update (synthetic events), optional open-loop evaluation.

A thin wrapper: the code is :mod:`dvsland.bench.stage_estimators` (also run by ``dvsland bench``);
this script hands it the ``dvsland`` command line, which ``--eval`` runs (``dvsland evaluate``).
``python scripts/bench_estimators.py --help`` lists the options.
"""

import sys

from dvsland.bench.stage_estimators import main
from dvsland.cli.main import main as dvsland_command

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:], run_command=dvsland_command))
