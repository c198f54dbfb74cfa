"""GR00T adapter for phone2act (N1.5 and N1.6 wire): observations out to a GR00T server, action chunks back in."""

from phone2act_gr00t.adapter import AdapterStats, Gr00tAdapter, MissingTaskError, StepResult
from phone2act_gr00t.embodiment import (
    ActionGroup,
    ChunkShapeError,
    Embodiment,
    EmbodimentMismatch,
    Group,
    NonFiniteActionError,
    ObservationError,
)
from phone2act_gr00t.modes import ActionModeError, action_mode_of
from phone2act_gr00t.wire import (
    N15,
    N16,
    N16_SIM,
    Gr00tClient,
    Gr00tError,
    Gr00tProtocolError,
    Gr00tTimeout,
    ModalityConfig,
    check_forced_wire,
    packb,
    unpackb,
)

__all__ = [
    "N15",
    "N16",
    "N16_SIM",
    "ActionGroup",
    "ActionModeError",
    "AdapterStats",
    "ChunkShapeError",
    "Embodiment",
    "EmbodimentMismatch",
    "Gr00tAdapter",
    "Gr00tClient",
    "Gr00tError",
    "Gr00tProtocolError",
    "Gr00tTimeout",
    "Group",
    "MissingTaskError",
    "ModalityConfig",
    "NonFiniteActionError",
    "ObservationError",
    "StepResult",
    "action_mode_of",
    "check_forced_wire",
    "packb",
    "unpackb",
]
