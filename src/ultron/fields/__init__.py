"""Acoustic neural fields (stage 1, Ultra-NeRF): named properties and backends (the fitted
field with its renderer is :mod:`ultron.models`)."""

from ultron.fields.base import AcousticField
from ultron.fields.factory import BACKENDS, FieldConfig, build_field
from ultron.fields.grid import GridField, GridFieldConfig
from ultron.fields.mlp import MLPField, MLPFieldConfig
from ultron.fields.networks import PositionalEncoding, SkipMLP
from ultron.fields.properties import (
    CHANNELS,
    CHANNELS_WITH_DENSITY,
    AcousticProperties,
    properties_from_raw,
)

__all__ = [
    "BACKENDS",
    "CHANNELS",
    "CHANNELS_WITH_DENSITY",
    "AcousticField",
    "AcousticProperties",
    "FieldConfig",
    "GridField",
    "GridFieldConfig",
    "MLPField",
    "MLPFieldConfig",
    "PositionalEncoding",
    "SkipMLP",
    "build_field",
    "properties_from_raw",
]
