"""The daemon's configuration: one TOML file, validated once at start-up into typed objects.

A file starts with ``schema_version = 1`` and holds the sections ``[cell]``, ``[robot]``,
``[sensor]`` (with a driver-specific ``[sensor.options]`` table), optionally ``[table]``, then
``[sync]``, ``[pipeline]``, ``[zenoh]``, ``[calibration]`` and, for the simulated cell, ``[sim]``.
``config/sim.toml`` is the commented reference; it ships inside the package as
``default_sim.toml`` so that :func:`load_default` needs no file on disk.

Every value is checked here, with ranges, so that the rest of the daemon can trust it: unknown
keys are errors (typos must not be silently ignored), numbers must be finite, units are SI and
part of the field names (``_m``, ``_s``, ``_hz``, ``_rad``, ``_deg``). A bad file raises one
:class:`ConfigError` that lists every problem as one readable line::

    config/sim.toml: robot.max_speed_m_s: must be > 0 (got -1)

Relative paths (calibration files, an extra zenoh config) are resolved against the folder of the
config file.

The package holds one module per group of sections; import the names from here:

* :mod:`.values`   - the strict value types and the base model every section is built from;
* :mod:`.hardware` - ``[cell]``, ``[robot]``, ``[sensor]``, ``[table]``;
* :mod:`.service`  - ``[sync]``, ``[pipeline]``, ``[zenoh]``, ``[calibration]``;
* :mod:`.sim`      - ``[sim]``;
* :mod:`.loading`  - the root :class:`Config`, :func:`parse_config`, :func:`load_config`,
  :func:`load_default`;
* :mod:`.errors`   - :class:`ConfigError` and the one-line-per-problem formatting.
"""

from wristscan.daemon.config.errors import ConfigError, format_validation_error
from wristscan.daemon.config.hardware import (
    CellConfig,
    GocatorSensorConfig,
    Lpf1SerialOptions,
    Lpf1SerialSensorConfig,
    Lpf1TcpOptions,
    Lpf1TcpSensorConfig,
    Lpf1UdpOptions,
    Lpf1UdpSensorConfig,
    PluginSensorConfig,
    Rf627Options,
    Rf627SensorConfig,
    RobotConfig,
    ScipOptions,
    ScipSensorConfig,
    SensorConfig,
    TableConfig,
)
from wristscan.daemon.config.loading import (
    DEFAULT_CONFIG_RESOURCE,
    SCHEMA_VERSION,
    Config,
    load_config,
    load_default,
    parse_config,
)
from wristscan.daemon.config.service import (
    CalibrationConfig,
    PipelineConfig,
    SyncConfig,
    ZenohConfig,
)
from wristscan.daemon.config.sim import (
    SimConfig,
    SimControllerConfig,
    SimSceneConfig,
    SimSensorConfig,
    SimTableConfig,
    SimTruthConfig,
)

__all__ = [
    "DEFAULT_CONFIG_RESOURCE",
    "SCHEMA_VERSION",
    "CalibrationConfig",
    "CellConfig",
    "Config",
    "ConfigError",
    "GocatorSensorConfig",
    "Lpf1SerialOptions",
    "Lpf1SerialSensorConfig",
    "Lpf1TcpOptions",
    "Lpf1TcpSensorConfig",
    "Lpf1UdpOptions",
    "Lpf1UdpSensorConfig",
    "PipelineConfig",
    "PluginSensorConfig",
    "Rf627Options",
    "Rf627SensorConfig",
    "RobotConfig",
    "ScipOptions",
    "ScipSensorConfig",
    "SensorConfig",
    "SimConfig",
    "SimControllerConfig",
    "SimSceneConfig",
    "SimSensorConfig",
    "SimTableConfig",
    "SimTruthConfig",
    "SyncConfig",
    "TableConfig",
    "ZenohConfig",
    "format_validation_error",
    "load_config",
    "load_default",
    "parse_config",
]
