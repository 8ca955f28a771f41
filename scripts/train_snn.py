#!/usr/bin/env python
"""Train the spiking divergence estimator ('snn'): the same as ``dvsland train`` (kept for old
command lines; the options, the data and where the checkpoint goes are those of the command).

    python scripts/train_snn.py [--n-seq 1280] [--steps 20] [--epochs 14] [--init CKPT] [--out PATH]

Without ``--out`` the checkpoint goes into a new run folder under logs/; the shipped checkpoint
inside the package is only replaced with ``--overwrite-shipped`` (docs/estimators_snn.md).
"""

from __future__ import annotations

import sys


def main(argv=None) -> int:
    from dvsland.cli.main import main as dvsland_main

    return dvsland_main(["train", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
