"""Acoustic neural fields (stage 1, Ultra-NeRF): named properties, backends, fitted fields."""

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

# The fitted-field API depends on ultron.render, which itself uses ultron.fields.base and
# ultron.fields.properties: load it lazily to keep the import graph acyclic.
_FITTED = ("FieldMaps", "FittedField", "ThetaStatistics", "load_field")
__all__ += list(_FITTED)


def __getattr__(name: str) -> object:
    if name in _FITTED:
        from ultron.fields import fitted

        return getattr(fitted, name)
    raise AttributeError(f"module 'ultron.fields' has no attribute {name!r}")
