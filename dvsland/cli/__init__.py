"""The ``dvsland`` command line. Each ``cmd_<name>.py`` module here adds one sub-command
through its ``register(subparsers)`` function; :mod:`dvsland.cli.main` discovers them."""
