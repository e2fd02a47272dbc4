"""ultron: Ultrasound Occupancy Networks.

Turns tracked, multiview 2D ultrasound sweeps into 3D surface meshes of anatomy (UltrON,
"Ultrasound Occupancy Networks"), with its baselines, a digital phantom simulator and metrics.
"""

from ultron.errors import UltronError, UltronInputError

__version__ = "0.1.0"

__all__ = ["UltronError", "UltronInputError", "__version__"]
