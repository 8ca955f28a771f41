"""Typed, validated configuration (YAML in ``configs/`` -> dataclasses).

Public names: :class:`Config` and its sections, :func:`load_config`, :func:`apply_overrides`,
:func:`dump_config`, :func:`config_to_dict`, :class:`ConfigError`, :func:`configs_dir`,
:func:`validate_config` (the one check every entry point runs).
"""

from .loader import (apply_overrides, config_to_dict, configs_dir, dump_config, load_config, read_yaml,
                     repo_root, resolve_config_path)
from .schema import (PAPER_INITIAL_CONDITIONS, SITE_NAMES, CameraConfig, CMaxConfig, Config, ControllerConfig,
                     ControllerSetting,
                     DPRConfig, DynamicsConfig, EmulatorConfig, EstimatorConfig, LoggingConfig,
                     OracleConfig, RenderConfig, SimulationConfig, SiteConfig, SNNConfig)
from .errors import ConfigError
from .validate import build, validate_config

__all__ = [
    "Config", "CameraConfig", "RenderConfig", "EmulatorConfig", "EstimatorConfig", "DPRConfig",
    "CMaxConfig", "OracleConfig", "SNNConfig", "ControllerConfig", "ControllerSetting", "DynamicsConfig",
    "SimulationConfig", "SiteConfig", "LoggingConfig", "SITE_NAMES", "PAPER_INITIAL_CONDITIONS", "ConfigError",
    "load_config",
    "apply_overrides", "dump_config", "config_to_dict", "configs_dir", "repo_root", "read_yaml", "build",
    "resolve_config_path", "validate_config",
]
