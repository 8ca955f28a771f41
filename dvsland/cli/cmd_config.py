"""``dvsland config show [CONFIG] [--set ...]``: print the resolved, validated config."""

from __future__ import annotations

from dvsland.config import dump_config

from .common import add_config_args, config_from_args


def register(subparsers) -> None:
    p = subparsers.add_parser("config", help="inspect configurations")
    sub = p.add_subparsers(dest="config_cmd", required=True)
    show = sub.add_parser("show", help="print the resolved, validated config as YAML")
    add_config_args(show, out=False)
    show.set_defaults(func=run_show)


def run_show(args) -> int:
    from dvsland.stages import check_names

    cfg = config_from_args(args)
    check_names(cfg)  # stage names are checked against the registries, where stages are built
    print(dump_config(cfg), end="")
    return 0
