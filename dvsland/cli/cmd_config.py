"""``dvsland config show [CONFIG] [--set ...] [--origin]``: print the resolved, validated config,
with ``--origin`` the file (or ``--set``) each value came from."""

from __future__ import annotations

from dvsland.config import dump_config

from .common import add_config_args, config_from_args


def register(subparsers) -> None:
    p = subparsers.add_parser("config", help="inspect configurations")
    sub = p.add_subparsers(dest="config_cmd", required=True)
    show = sub.add_parser(
        "show", help="print the resolved, validated config as YAML",
        description="Print the config a run would use: the file, the presets it extends (extends: NAME), "
                    "and the --set overrides, validated. --origin adds a comment after each value naming "
                    "the file it came from, the --set that changed it, or 'default'.")
    add_config_args(show, out=False)
    show.add_argument("--origin", action="store_true",
                      help="after each value, the file (or --set, or default) it came from")
    show.set_defaults(func=run_show)


def run_show(args) -> int:
    from dvsland.config.loader import dump_config_with_origins, load_config_with_origins
    from dvsland.stages import check_names

    cfg = config_from_args(args)
    check_names(cfg)  # stage names are checked against the registries, where stages are built
    if args.origin:
        _, origins = load_config_with_origins(args.config, list(args.overrides or []))
        print(dump_config_with_origins(cfg, origins), end="")
    else:
        print(dump_config(cfg), end="")
    return 0
