"""Monte Carlo campaigns: the grid of swept values x seeds, split into shards (one batch each),
run locally or on Ray, merged into one report with success rates and Wilson intervals.

Public names: :func:`run_campaign`, :class:`CampaignResult`, :class:`CampaignPlan`,
:class:`Shard`, :func:`make_plan`, :func:`run_shard`, :func:`ray_available`.
"""

from .executors import ray_available
from .plan import CampaignPlan, Shard, make_plan, parse_sweep
from .runner import CampaignResult, merge, run_campaign
from .shard import run_shard, velocity_at_altitude

__all__ = ["run_campaign", "CampaignResult", "CampaignPlan", "Shard", "make_plan", "parse_sweep", "run_shard",
           "merge", "ray_available", "velocity_at_altitude"]
