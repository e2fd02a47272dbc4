"""Models: a fitted acoustic field joined to the scanline renderer (nerfstudio's ``models``).

:class:`FittedField` reads a FIELD_DIR (``fit-field``'s output) and renders B-mode frames,
θ and transmission maps at any probe pose; ``fields`` (the networks) and ``render`` (the
physics) stay independent of each other.
"""

from ultron.models.fitted import FieldMaps, FittedField, ThetaStatistics, load_field

__all__ = ["FieldMaps", "FittedField", "ThetaStatistics", "load_field"]
