#!/usr/bin/env python
"""A user-written thrust law, registered by name and flown in the closed loop.

The law ("div_backoff") is the paper's released divergence law, u = Kp (D* - D) + m g, with an
adaptive gain that backs off when the loop oscillates by itself: the released law's gain Kp/(m z)
grows as the craft descends until the 10 Hz loop rings (the sign of the error flips every step).
Each flip halves a per-descent gain factor; each step without one lets it recover by 2 %, up to 1.

Everything a controller needs: ``from_params(params, **options)`` (the loop hands it a
``DescentParams``: per-descent Kp, n_bin, tau0, z0, v0, m0 tensors plus c2, g, dt and the thrust
bounds), ``reset(mask)`` and ``__call__(t_s, d_filtered, mass_kg, active)`` returning a
``ControlOutput``. Options come from ``controller.params`` in the config (``--set
controller.params.backoff=0.5``).

Usage:
    python scripts/custom_controller.py                          # oracle, sites A and D, paper preset
    python scripts/custom_controller.py --estimator dpr --sites D,E

To ship such a law in a package instead, declare it under the entry-point group
``dvsland.controllers`` (pyproject.toml: ``[project.entry-points."dvsland.controllers"]
div_backoff = "mypkg.backoff:DivBackoff"``) and select it with ``controller.name: div_backoff``
or ``dvsland simulate --controller div_backoff``.
"""

from __future__ import annotations

import argparse

import torch

from dvsland.control import ControlOutput, Controller, register_controller


@register_controller("div_backoff")
class DivBackoff(Controller):
    """u = k Kp (-1/tau*(t) - D) + m g, k in [k_min, 1] halved on every sign flip of the error."""

    def __init__(self, p, backoff=0.5, recover=1.02, k_min=0.01):
        self.p, self.backoff, self.recover, self.k_min = p, float(backoff), float(recover), float(k_min)
        self.reset()

    @classmethod
    def from_params(cls, p, **options):
        return cls(p, **options)

    def reset(self, mask=None):
        ones = torch.ones_like(self.p.kp)
        if mask is None:
            self.k, self.last_e, self.last_u = ones, torch.zeros_like(ones), None
        else:
            self.k = torch.where(mask, ones, self.k)
            self.last_e = torch.where(mask, 0.0, self.last_e)

    def __call__(self, t_s, d_filtered, mass_kg, active=None):
        p = self.p
        tau_star = p.tau0_s - p.c2 * t_s
        ok = ~torch.isnan(d_filtered)
        e = torch.where(ok, -1.0 / tau_star - d_filtered, 0.0)
        flipped = ok & (e * self.last_e < 0)
        self.k = torch.where(flipped, self.k * self.backoff, (self.k * self.recover).clamp_max(1.0)).clamp_min(self.k_min)
        self.last_e = torch.where(ok, e, self.last_e)
        u = (self.k * p.kp * e + mass_kg * p.g_mps2).clamp_min(p.thrust_min_n)
        if p.thrust_max_n is not None:
            u = u.clamp_max(p.thrust_max_n)
        hover = mass_kg * p.g_mps2
        u = torch.where(ok, u, hover if self.last_u is None else self.last_u)  # no estimate: hold (hover at first)
        if active is not None and self.last_u is not None:
            u = torch.where(active, u, self.last_u)
        self.last_u = u
        return ControlOutput(thrust_n=u, tau_hat_s=torch.where(d_filtered < 0, -1.0 / d_filtered, float("nan")),
                             tau_target_s=tau_star.expand_as(u) if torch.is_tensor(tau_star) else tau_star, held=~ok)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="paper", help="config (default: the paper preset)")
    ap.add_argument("--estimator", default="oracle", help="divergence estimator (default oracle)")
    ap.add_argument("--sites", default="A,D", help="sites to fly (default A,D)")
    ap.add_argument("--out", default=None, help="run folder")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)

    import dvsland

    result = dvsland.simulate(args.config, controller="div_backoff", estimator=args.estimator, sites=args.sites,
                              out=args.out, quiet=args.quiet)
    for r in result.runs:
        print(f"{r['run']}: {r['outcome']} at t = {r['t_end_s']:.1f} s, lowest {r['lowest_altitude_m']:.1f} m, "
              f"v_end {r['v_end_mps']:.2f} m/s, max thrust {r['max_thrust_n'] / 1e3:.0f} kN")
    print(f"run folder: {result.run_dir}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
