"""Run configuration: schema, reading, cross-key checks and output (see :mod:`.schema`).

:mod:`~rths_hil.config.schema` (every key with its type, unit, range, default and doc; the
α ↔ delay key pairs), :mod:`~rths_hil.config.coerce` (one value to its key's type, unit and
range; :func:`check_table`, one table to its keys: the validator of configuration sections,
controller profiles and twin model files), :mod:`~rths_hil.config.model` (:class:`Config`
and its channels),
:mod:`~rths_hil.config.load` (files, ``[[actuators]]``, ``--set``),
:mod:`~rths_hil.config.checks` (every rule relating keys to each other),
:mod:`~rths_hil.config.output` (TOML and the markdown reference ``docs/config.md``).
"""

from ..keys import REQUIRED
from .checks import check_window_samples, cross_check, cross_check_channel, structure_dofs
from .coerce import check_range, check_table, coerce, describe, quantity, unknown_key
from .load import MAX_CONFIG_BYTES, apply_overrides, load_config, merge, parse_override
from .model import ChannelConfig, Config, default_config, resolve_channel
from .output import schema_markdown, to_toml, toml_value
from .schema import (
    CHANNEL_KEYS,
    CHANNEL_SECTIONS,
    MASS_RANGE,
    SCHEMA,
    STEP_KEYS,
    STEP_PAIR,
    STIFFNESS_RANGE,
    Key,
    check_compensation_units,
    set_compensation,
)

__all__ = [
    "CHANNEL_KEYS",
    "CHANNEL_SECTIONS",
    "MASS_RANGE",
    "MAX_CONFIG_BYTES",
    "REQUIRED",
    "SCHEMA",
    "STEP_KEYS",
    "STEP_PAIR",
    "STIFFNESS_RANGE",
    "ChannelConfig",
    "Config",
    "Key",
    "apply_overrides",
    "check_compensation_units",
    "check_range",
    "check_table",
    "check_window_samples",
    "coerce",
    "cross_check",
    "cross_check_channel",
    "default_config",
    "describe",
    "load_config",
    "merge",
    "parse_override",
    "quantity",
    "resolve_channel",
    "schema_markdown",
    "set_compensation",
    "structure_dofs",
    "to_toml",
    "toml_value",
    "unknown_key",
]
