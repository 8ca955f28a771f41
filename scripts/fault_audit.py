"""Fault audit: bad and extreme inputs, each run as a fresh ``dvsland`` command (config values: in
one process through ``dvsland.cli.main.main``, which is the same code path), classified by what
came back.

    python scripts/fault_audit.py [--classes config,flags,plugins,recordings,campaign,interrupts,disk,sizes]
                                  [--out audit.json] [--timeout 90]

Outcome of one input:
    refused     exit 2, one line on stderr (progress bars aside), no traceback: a clear error
    ran         exit 0 (for a valid input); for an invalid one it is counted as ``silent``
    long-run    (in-range config extremes, flown in process) still running at 30 s, and stopped by the
                time limit's signal: valid, slow, interruptible
    stopped     (interrupt cases) the command ended within 2 s of SIGINT / SIGTERM, run folder kept
    slow-stop   (interrupt cases) it ended, but later than 2 s after the signal
    traceback   a Python traceback on stderr
    hang        no end within the time limit
    nan-leak    exit 0 but results.json holds a non-finite final state of a finished descent
    crash       anything else (a signal, another exit code)

Prints a table of counts per class and writes every case with its outcome to ``--out``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import typing
from pathlib import Path
from typing import Callable, List, Optional

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYOPENGL_PLATFORM": "egl", "EGL_PLATFORM": "surfaceless", "PYTHONWARNINGS": "ignore"}
SHORT = ["--set", "simulation.t_max_s=2", "--set", "logging.tensorboard=false", "--set", "logging.figures=false"]


@dataclasses.dataclass
class Case:
    cls: str
    name: str
    argv: List[str]
    invalid: bool = True
    setup: Optional[Callable[[Path], None]] = None
    signal_after_s: Optional[float] = None
    signum: int = signal.SIGINT
    outcome: str = ""
    detail: str = ""
    seconds: float = 0.0


def _one_line(err: str) -> List[str]:
    return [ln for ln in err.strip().splitlines() if ln.strip() and "%|" not in ln and "it/s]" not in ln]


def _nan_leak(folder: Path) -> bool:
    """A bare NaN / Infinity token in a JSON output, or a finished descent whose final state is null."""
    for name in ("results.json", "evaluation.json"):
        p = folder / name
        if not p.is_file():
            continue
        tokens: list = []
        data = json.loads(p.read_text(), parse_constant=lambda c: tokens.append(c))
        if tokens:
            return True
        for run in (data.get("runs", []) if isinstance(data, dict) else []):
            if run.get("outcome") in ("success", "crash") and any(run.get(k) is None for k in ("z_end_m", "v_end_mps")
                                                                  if k in run):
                return True
    return False


def classify(rc: Optional[int], err: str, invalid: bool, folder: Path) -> str:
    if rc is None:
        return "hang"
    if "Traceback (most recent call last)" in err:
        return "traceback"
    lines = _one_line(err)
    argparse_error = len(lines) >= 2 and lines[0].startswith("usage:") and ": error: " in lines[-1]
    if rc == 2 and (len(lines) <= 2 or argparse_error):
        return "refused"
    if rc == 0:
        if _nan_leak(folder):
            return "nan-leak"
        return "silent" if invalid else "ran"
    return "crash"


def run_fresh(case: Case, work: Path, timeout_s: float) -> None:
    folder = work / "out"
    argv = [a.replace("{OUT}", str(folder)).replace("{WORK}", str(work)) for a in case.argv]
    if case.setup:
        case.setup(work)
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "dvsland.cli.main", *argv], cwd=REPO, env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        if case.signal_after_s is not None:
            try:  # the signal goes signal_after_s after the run folder exists (past the imports)
                deadline = time.monotonic() + timeout_s
                while not (folder / "config.yaml").is_file() and time.monotonic() < deadline and proc.poll() is None:
                    time.sleep(0.1)
                proc.wait(case.signal_after_s)
                case.outcome, case.detail = "ended-before-signal", ""
            except subprocess.TimeoutExpired:
                os.kill(proc.pid, case.signum)
                ts = time.monotonic()
                try:
                    proc.wait(timeout_s)
                    stop_s = time.monotonic() - ts
                    err = proc.stderr.read()
                    kept = (folder / "config.yaml").is_file() or not folder.exists()
                    tb = "Traceback (most recent call last)" in err
                    case.outcome = "traceback" if tb else ("stopped" if stop_s <= 2.0 and kept else "slow-stop")
                    case.detail = f"stopped in {stop_s:.2f} s; " + (_one_line(err) or [""])[-1][:200]
                except subprocess.TimeoutExpired:
                    case.outcome, case.detail = "hang", "no end after the signal"
            return
        try:
            rc = proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            rc = None
        err = proc.stderr.read() if rc is not None else ""
        case.outcome = classify(rc, err, case.invalid, folder)
        lines = _one_line(err)
        case.detail = (lines[-1] if lines else f"rc={rc}")[:240]
    finally:
        case.seconds = time.monotonic() - t0
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


# ------------------------------------------------------------------ config values (in process)
def config_cases() -> List[Case]:
    from dvsland.config import Config
    from dvsland.config.schema import LIST_ITEM_TYPES
    from dvsland.config.validate import _strip_optional

    def leaves(cls=Config, prefix=()):
        out = []
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            tp, _ = _strip_optional(hints[f.name])
            path = prefix + (str(f.name),)
            if dataclasses.is_dataclass(tp):
                out += leaves(tp, path)
            elif tp is list:
                item = LIST_ITEM_TYPES.get((cls, f.name))
                if item is not None:
                    out += leaves(item, path + ("0",))
            elif tp in (int, float):
                out.append((".".join(path), f.metadata, tp))
        return out

    cases = []
    for key, md, tp in leaves():
        lo, hi = md.get("rng") or (-math.inf, math.inf)
        bad = ["nan", "inf", "-inf", "abc", "[1,2]"] + (["1.5"] if tp is int else [])
        if math.isfinite(lo):
            bad.append(repr(lo - max(1.0, abs(lo)) * 0.5) if not md.get("open_lo") else repr(lo))
        if math.isfinite(hi):
            bad.append(repr(hi + max(1.0, abs(hi)) * 0.5) if not md.get("open_hi") else repr(hi))
        for v in bad:
            cases.append(Case("config", f"{key}={v}", ["config", "show", "paper", "--set", f"{key}={v}"]))
        # extremes inside the range must run (or be refused up front): flown briefly
        for v in {x for x in (lo, hi) if math.isfinite(x)} | ({5e-324} if lo <= 0 < hi and tp is float else set()):
            if (v == lo and md.get("open_lo")) or (v == hi and md.get("open_hi")):
                continue
            val = str(int(v)) if tp is int else repr(v)
            cases.append(Case("config-extreme", f"{key}={val}", ["simulate", "paper", "--sites", "A", "--quiet",
                                                                 "--out", "{OUT}", "--set", f"{key}={val}"] + SHORT,
                              invalid=False))
    return cases


class AuditTimeout(BaseException):
    """The time limit of an in-process case (raised by SIGALRM between two bytecodes)."""


def run_in_process(case: Case, work: Path, timeout_s: float) -> None:
    from dvsland.cli.main import main

    argv = [a.replace("{OUT}", str(work / "out")) for a in case.argv]
    err, out = io.StringIO(), io.StringIO()

    def alarm(signum, frame):
        raise AuditTimeout()  # a BaseException: no `except Exception` inside dvsland swallows it

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(int(timeout_s))
    t0 = time.monotonic()
    rc: Optional[int]
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            rc = main(argv)
    except AuditTimeout:
        rc = -1
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else 2
    except BaseException as exc:  # noqa: BLE001 - what escapes main() is a traceback to the user
        import traceback

        err.write("Traceback (most recent call last)\n" + "".join(traceback.format_exception(exc)))
        rc = 1
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    case.seconds = time.monotonic() - t0
    # an in-range extreme still flying at the limit (e.g. 10 kHz control) was interruptible: "long-run"
    case.outcome = "long-run" if rc == -1 else classify(rc, err.getvalue(), case.invalid, work / "out")
    lines = _one_line(err.getvalue())
    case.detail = (lines[-1] if lines else f"rc={rc}")[:240]


# ------------------------------------------------------------------ fresh commands
BASE = {
    "simulate": ["simulate", "paper", "--sites", "A", "--quiet", "--out", "{OUT}"] + SHORT,
    "campaign": ["campaign", "paper", "--sites", "A", "--n-seeds", "1", "--quiet", "--out", "{OUT}"] + SHORT,
    "evaluate": ["evaluate", "paper", "--sites", "A", "--estimators", "dpr", "--max-steps", "10", "--out", "{OUT}",
                 "--set", "logging.tensorboard=false"],
    "events": ["events", "paper", "--sites", "A", "--out", "{OUT}", "--set", "logging.tensorboard=false"],
    "render": ["render", "paper", "--sites", "A", "--quiet", "--out", "{OUT}"],
    "dataset build": ["dataset", "build", "paper", "--sites", "A", "--n-seeds", "1", "--out", "{OUT}"] + SHORT,
}


def flag_cases() -> List[Case]:
    """Every int / float flag of the commands above: negative, NaN, inf, huge, text (0 is valid for some)."""
    from dvsland.cli.main import build_parser

    subs = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    cases = []
    for cmd, base in BASE.items():
        parser = subs[cmd.split()[0]]
        if " " in cmd:
            parser = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[cmd.split()[1]]
        for act in parser._actions:
            # int, float, or a range-checked parser (dvsland.cli.common.ranged) of either
            numeric = act.type in (int, float) or getattr(act.type, "__qualname__", "").startswith("ranged.")
            if not numeric or not act.option_strings or act.choices:
                continue
            flag = act.option_strings[-1]
            for v in ["-1", "nan", "inf", "1e18", "x", "0"]:
                if v in ("nan", "inf", "1e18") and act.type is int:
                    v = {"nan": "99999999999", "inf": "-99999999999", "1e18": "1000000000000000000"}[v]
                argv = [a for a in base]
                if flag in argv:  # replace the base's own value
                    i = argv.index(flag)
                    argv[i + 1] = v
                else:
                    argv += [flag, v]
                cases.append(Case("flags", f"{cmd} {flag} {v}", argv, invalid=v != "0"))
    return cases


PLUGIN_SRC = '''
import sys
import numpy as np
import torch

class Base:
    needs_events = False
    def __init__(self, batch_size, sensor_size=None, device="cpu", **kw):
        self.batch_size = batch_size
    def reset(self, mask=None):
        pass

def _make(ret):
    class P(Base):
        def update(self, events, t_us, truth=None):
            return ret(self)
    return P

WrongLength = _make(lambda s: torch.zeros(s.batch_size + 1))
TwoD = _make(lambda s: torch.zeros(s.batch_size, 1))
Scalar = _make(lambda s: -0.1)
AList = _make(lambda s: [-0.1] * s.batch_size)
ATuple = _make(lambda s: tuple([-0.1] * s.batch_size))
Numpy = _make(lambda s: np.full(s.batch_size, -0.1))
NoneRet = _make(lambda s: None)
AStr = _make(lambda s: "x")
Bool = _make(lambda s: torch.ones(s.batch_size, dtype=torch.bool))
Complex = _make(lambda s: torch.zeros(s.batch_size, dtype=torch.complex64))
Meta = _make(lambda s: torch.zeros(s.batch_size, device="meta"))
Grad = _make(lambda s: torch.full((s.batch_size,), -0.1, requires_grad=True) * 1.0)
Int = _make(lambda s: torch.zeros(s.batch_size, dtype=torch.int64))
AllNaN = _make(lambda s: torch.full((s.batch_size,), float("nan")))
Inf = _make(lambda s: torch.full((s.batch_size,), float("inf")))
Raises = _make(lambda s: 1 / 0)
Exits = _make(lambda s: sys.exit(3))

class Recurses(Base):
    def update(self, events, t_us, truth=None):
        return self.update(events, t_us, truth)

class Huge(Base):
    def update(self, events, t_us, truth=None):
        return torch.empty(1 << 40)

class InitRaises(Base):
    def __init__(self, *a, **kw):
        raise RuntimeError("no")

class ResetRaises(Base):
    def reset(self, mask=None):
        raise KeyError("state")
    def update(self, events, t_us, truth=None):
        return torch.zeros(self.batch_size)

class BadConfidence(Base):
    def update(self, events, t_us, truth=None):
        return torch.zeros(self.batch_size)
    def confidence(self):
        return "high"

class NaNConfidence(Base):
    def update(self, events, t_us, truth=None):
        return torch.zeros(self.batch_size)
    def confidence(self):
        return torch.full((self.batch_size,), float("nan"))

class NotAnEstimator:
    def __init__(self, *a, **kw):
        pass

def factory_none(*a, **kw):
    return None
'''

PLUGINS = ["WrongLength", "TwoD", "Scalar", "AList", "ATuple", "Numpy", "NoneRet", "AStr", "Bool", "Complex", "Meta",
           "Int", "Raises", "Exits", "Recurses", "Huge", "InitRaises", "ResetRaises", "BadConfidence", "NotAnEstimator",
           "factory_none", "Missing"]
VALID_PLUGINS = ["Grad", "AllNaN", "Inf", "NaNConfidence"]  # legal: detached / treated as no estimate


def plugin_cases() -> List[Case]:
    def setup(work: Path) -> None:
        (work / "plugs.py").write_text(PLUGIN_SRC)

    cases = []
    for name in PLUGINS + VALID_PLUGINS:
        argv = ["simulate", "paper", "--sites", "A", "--quiet", "--out", "{OUT}", "--estimator",
                f"{{WORK}}/plugs.py:{name}"] + SHORT
        cases.append(Case("plugins", name, argv, invalid=name in PLUGINS, setup=setup))
    for spec in ["builtins:print", "collections:OrderedDict", "os:path", "nonexistent.module:X", "plugs.py",
                 ":", "=dpr", "a b=dpr"]:
        cases.append(Case("plugins", spec, ["simulate", "paper", "--sites", "A", "--quiet", "--out", "{OUT}",
                                            "--estimator", spec] + SHORT))
    return cases


def _damage(raw: bytes, kind: str) -> bytes:
    n = len(raw)
    return {"empty": b"", "1byte": raw[:1], "half": raw[: n // 2], "garbage": os.urandom(max(64, n // 4)),
            "zero-run": raw[: n // 3] + bytes(min(4096, n // 3)) + raw[n // 3 + min(4096, n // 3):],
            "flip16": bytes(b ^ 0xFF if (i - n // 2) in range(16) else b for i, b in enumerate(raw))}[kind]


def recording_cases() -> List[Case]:
    cases = []
    for src in sorted((REPO / "tests" / "data").glob("descent_A.*")):
        for kind in ("empty", "1byte", "half", "garbage", "zero-run", "flip16"):
            def setup(work: Path, src=src, kind=kind) -> None:
                (work / f"rec{src.suffix}").write_bytes(_damage(src.read_bytes(), kind))

            cases.append(Case("recordings", f"{src.name} {kind}",
                              ["evaluate", "paper", "--recording", f"{{WORK}}/rec{src.suffix}", "--estimators", "dpr",
                               "--max-steps", "5", "--out", "{OUT}", "--set", "logging.tensorboard=false"],
                              invalid=kind in ("empty", "1byte", "garbage"), setup=setup))
    csv_rows = {"x-at-width": "t_us,x,y,p\n1,128,5,1\n2,3,4,0\n", "x-32767": "t_us,x,y,p\n1,32767,5,1\n",
                "coord-1e18": "t_us,x,y,p\n1,1000000000000000000,5,1\n", "t-2^63": "t_us,x,y,p\n9223372036854775808,1,1,1\n",
                "latin1": "t_us,x,y,p\n1,2,3,1\n\xe9\xe8\n", "cut-mid-line": "t_us,x,y,p\n1,2,3,1\n2,3,",
                "nan-t": "t_us,x,y,p\nnan,2,3,1\n"}
    for name, text in csv_rows.items():
        def setup(work: Path, text=text) -> None:
            (work / "rec.csv").write_bytes(text.encode("latin-1"))

        cases.append(Case("recordings", f"csv {name}", ["evaluate", "paper", "--recording", "{WORK}/rec.csv",
                                                        "--estimators", "dpr", "--max-steps", "5", "--out", "{OUT}",
                                                        "--set", "camera.width_px=128", "--set", "camera.height_px=128",
                                                        "--set", "logging.tensorboard=false"], setup=setup))
    return cases


def campaign_cases() -> List[Case]:
    """A finished tiny campaign, then its plan or shards damaged, then --resume."""
    def make(damage: Callable[[Path], None]):
        def setup(work: Path) -> None:
            subprocess.run([sys.executable, "-m", "dvsland.cli.main", "campaign", "paper", "--sites", "A",
                            "--n-seeds", "2", "--shard-seeds", "1", "--quiet", "--out", str(work / "c"), *SHORT],
                           cwd=REPO, env=ENV, capture_output=True)
            damage(work / "c")
        return setup

    def shard(c: Path) -> Path:
        return sorted((c / "shards").glob("*.json"))[0]

    damages = {
        "plan empty": lambda c: (c / "campaign.json").write_text(""),
        "plan truncated": lambda c: (c / "campaign.json").write_text((c / "campaign.json").read_text()[:40]),
        "plan garbage": lambda c: (c / "campaign.json").write_bytes(os.urandom(200)),
        "plan list": lambda c: (c / "campaign.json").write_text("[1, 2]"),
        "shard list": lambda c: shard(c).write_text("[]"),
        "shard no runs": lambda c: shard(c).write_text(json.dumps({"id": shard(c).stem, "status": "complete"})),
        "shard runs wrong type": lambda c: shard(c).write_text(json.dumps({"id": shard(c).stem, "status": "complete",
                                                                           "runs": "x"})),
        "shard garbage": lambda c: shard(c).write_bytes(os.urandom(100)),
        "shards missing": lambda c: [p.unlink() for p in (c / "shards").glob("*.json")],
        "foreign shard": lambda c: shard(c).write_text(shard(c).read_text().replace('"config_hash": "',
                                                                                     '"config_hash": "0')),
    }
    # a damaged plan must be refused; a damaged or missing shard is reported and flown again (exit 0)
    return [Case("campaign", name, ["campaign", "--resume", "{WORK}/c", "--quiet"], invalid=name.startswith("plan"),
                 setup=make(d)) for name, d in damages.items()]


def interrupt_cases() -> List[Case]:
    long_ = ["--set", "simulation.t_max_s=300", "--set", "logging.tensorboard=true"]
    cmds = {
        "simulate": ["simulate", "paper", "--quiet", "--out", "{OUT}"] + long_,
        "campaign 2 workers": ["campaign", "paper", "--n-seeds", "4", "--workers", "2", "--quiet", "--out", "{OUT}"],
        "evaluate": ["evaluate", "paper", "--estimators", "dpr,cmax", "--out", "{OUT}"],
        "events": ["events", "paper", "--out", "{OUT}"],
        "dataset build": ["dataset", "build", "paper", "--n-seeds", "3", "--out", "{OUT}"],
        "bench": ["bench", "closed_loop", "--out", "{OUT}"],
        "n_bin at bound": ["simulate", "paper", "--sites", "A", "--quiet", "--out", "{OUT}", "--set",
                           "controller.settings.0.n_bin=10000"],
        "n-seeds 1e9": ["campaign", "paper", "--n-seeds", "1000000000", "--quiet", "--out", "{OUT}"],
    }
    return [Case("interrupts", f"{name} {signal.Signals(s).name}", argv, signal_after_s=after, signum=s)
            for name, argv in cmds.items() for s in (signal.SIGINT, signal.SIGTERM) for after in (3.0,)]


def disk_cases() -> List[Case]:
    if os.geteuid() != 0 or not sys.platform.startswith("linux"):
        return []
    cases = []
    for cmd in ("simulate", "campaign", "evaluate", "events", "render", "dataset build"):
        for size in ("16k", "48k", "200k", "1m"):
            def setup(work: Path, size=size) -> None:
                (work / "out").mkdir()
                subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(work / "out")], check=True)

            argv = [a.replace("{OUT}", "{OUT}/run") for a in BASE[cmd]]
            cases.append(Case("disk", f"{cmd} {size}", argv, invalid=False, setup=setup))
    return cases


def size_cases() -> List[Case]:
    sets = ["camera.width_px=4096", "camera.height_px=4096", "estimator.cmax.n_grid=2001", "render.threads=256",
            "simulation.torch_threads=256", "estimator.cmax.radial_bin_px=5e-324", "dynamics.isp_s=1e-320",
            "dynamics.g0_mps2=1e-320", "simulation.sites.0.z0_m=5e-324", "name=" + "x" * 5000,
            "estimator.snn.checkpoint=" + "/x" * 2500, "simulation.n_seeds=100000000"]
    cases = [Case("sizes", s[:60], ["simulate", "paper", "--sites", "A", "--quiet", "--out", "{OUT}", "--set", s]
                  + SHORT, invalid=False) for s in sets]
    cases += [Case("sizes", f"campaign --n-seeds {n}", ["campaign", "paper", "--n-seeds", n, "--quiet", "--out", "{OUT}"])
              for n in ("1000000000", "-5")]
    cases += [Case("sizes", "evaluate --threads 100000", BASE["evaluate"] + ["--threads", "100000"]),
              Case("sizes", "render --gif-frames 1e8", BASE["render"] + ["--gif-frames", "100000000"]),
              Case("sizes", "bench tradeoff bogus", ["bench", "tradeoff", "--estimators", "bogus", "--out", "{OUT}"]),
              Case("sizes", "long --out", ["simulate", "paper", "--out", "{WORK}/" + "y" * 300] + SHORT),
              Case("sizes", "events --window-ms -5", BASE["events"] + ["--window-ms", "-5"]),
              Case("sizes", "events --window-ms nan", BASE["events"] + ["--window-ms", "nan"]),
              Case("sizes", "events --max-points -1", BASE["events"] + ["--max-points", "-1"])]
    return cases


GENERATORS = {"config": config_cases, "flags": flag_cases, "plugins": plugin_cases, "recordings": recording_cases,
              "campaign": campaign_cases, "interrupts": interrupt_cases, "disk": disk_cases, "sizes": size_cases}


def run_case(case: Case, timeout_s: float) -> None:
    work = Path(tempfile.mkdtemp(prefix="dvsland-audit-"))
    try:
        if case.cls == "config" or case.cls == "config-extreme":
            run_in_process(case, work, min(timeout_s, 30.0))
        else:
            run_fresh(case, work, timeout_s)
    except Exception as exc:  # noqa: BLE001 - a broken case is reported, not fatal to the audit
        case.outcome, case.detail = "audit-error", f"{type(exc).__name__}: {exc}"[:240]
    finally:
        if (work / "out").is_mount():
            subprocess.run(["umount", str(work / "out")], capture_output=True)
        shutil.rmtree(work, ignore_errors=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--classes", default=",".join(GENERATORS))
    ap.add_argument("--out", default="audit.json")
    ap.add_argument("--timeout", type=float, default=90.0, help="seconds per input before it counts as a hang")
    args = ap.parse_args()
    os.environ.update({k: v for k, v in ENV.items() if k not in os.environ})
    cases: List[Case] = []
    for cls in args.classes.split(","):
        cases += GENERATORS[cls]()
    t0 = time.monotonic()
    for i, case in enumerate(cases):
        run_case(case, args.timeout)
        bad = case.outcome not in ("refused", "ran", "stopped")
        print(f"[{i + 1}/{len(cases)}] {case.cls:14s} {case.outcome:10s} {case.name[:70]}"
              + (f"  -- {case.detail[:160]}" if bad else ""), flush=True)
    counts: dict = {}
    for c in cases:
        counts.setdefault(c.cls, {}).setdefault(c.outcome, 0)
        counts[c.cls][c.outcome] += 1
    Path(args.out).write_text(json.dumps({"counts": counts, "seconds": time.monotonic() - t0,
                                          "cases": [dataclasses.asdict(c) | {"setup": None} for c in cases]},
                                         indent=1, default=str))
    print(json.dumps(counts, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
