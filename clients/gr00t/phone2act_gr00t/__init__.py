"""GR00T N1.5 adapter for phone2act: observations out to a GR00T inference server, action chunks back in."""

from phone2act_gr00t.adapter import AdapterStats, Gr00tAdapter, StepResult
from phone2act_gr00t.embodiment import ActionGroup, ChunkShapeError, Embodiment, ObservationError
from phone2act_gr00t.wire import Gr00tClient, Gr00tError, Gr00tTimeout, packb, unpackb

__all__ = [
    "ActionGroup",
    "AdapterStats",
    "ChunkShapeError",
    "Embodiment",
    "Gr00tAdapter",
    "Gr00tClient",
    "Gr00tError",
    "Gr00tTimeout",
    "ObservationError",
    "StepResult",
    "packb",
    "unpackb",
]
