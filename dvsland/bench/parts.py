"""The parts of ``dvsland bench`` by name: the report parts, the extra parts and the stage
benchmarks, and :func:`parse_what`. Imports nothing heavy, so the command line can list them in
its help without loading torch."""

from __future__ import annotations

from typing import List, Sequence

REPORT_PARTS = ("tradeoff", "closed_loop", "scaling", "economies")
#: parts run only when named (not in the default four)
EXTRA_PARTS = ("campaign",)

#: stage benchmarks: name -> (module, full args, quick args); "{json}" becomes the output path
STAGE_BENCHES = {
    "render": ("stage_render", ["--threads", "1", "--json", "{json}"],
               ["--threads", "1", "--batches", "18", "--repeat", "5", "--flicker-sites", "", "--json", "{json}"]),
    "events": ("stage_events", ["--threads", "1", "--json", "{json}"],
               ["--threads", "1", "--batch", "18", "--no-memory", "--no-real", "--json", "{json}"]),
    "v2e": ("stage_v2e", ["--threads", "1", "--json", "{json}"],
            ["--threads", "1", "--batch", "6", "--steps", "6", "--json", "{json}"]),
    "estimators": ("stage_estimators", ["--threads", "1", "--json", "{json}"],
                   ["--threads", "1", "--batch", "18", "--steps", "10", "--estimators", "dpr,oracle",
                    "--json", "{json}"]),
    "renderers": ("stage_renderers", ["--out", "{json}"], ["--n-alt", "4", "--segments", "--out", "{json}"]),
    "throughput": ("throughput", ["--device", "{device}", "--batches", "18,63,256", "--json", "{json}"],
                   ["--device", "{device}", "--batches", "18,63", "--steps", "10", "--estimators", "oracle,learned",
                    "--json", "{json}"]),
    "fleet": ("fleet", ["--device", "{device}", "--batch", "18", "--descents", "54", "--estimator", "learned",
                        "--json", "{json}"],
              ["--device", "{device}", "--batch", "9", "--descents", "18", "--estimator", "oracle", "--json", "{json}"]),
    "sim": ("stage_sim", ["--threads", "1", "--set", "render.threads=1", "--json", "{json}", "--out", "{dir}"],
            ["--threads", "1", "--set", "render.threads=1", "--sites", "A,D,H", "--json", "{json}", "--out", "{dir}"]),
}
ALIASES = {"closed-loop": "closed_loop", "closedloop": "closed_loop"}
CHOICES = REPORT_PARTS + EXTRA_PARTS + tuple(STAGE_BENCHES)


def parse_what(what: Sequence[str]) -> List[str]:
    """Normalise the WHAT arguments (default: the four report parts; ``all``: everything)."""
    names = [ALIASES.get(w.strip().replace("-", "_") if w.strip() not in ALIASES else w.strip(), w.strip())
             for w in (what or []) if w.strip()]
    if not names:
        return list(REPORT_PARTS)
    out = []
    for n in names:
        if n == "all":
            out += list(CHOICES)
        elif n in CHOICES:
            out.append(n)
        else:
            raise ValueError(f"unknown benchmark {n!r}; choose from all, {', '.join(CHOICES)}")
    return list(dict.fromkeys(out))


__all__ = ["REPORT_PARTS", "EXTRA_PARTS", "STAGE_BENCHES", "ALIASES", "CHOICES", "parse_what"]
