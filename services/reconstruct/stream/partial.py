"""What the live service keeps per scan in progress besides its assembly: the provisional estimate's state,
the stream's clocks, and the requests made to the acquirer's log for it."""

from __future__ import annotations

from dataclasses import dataclass, field

from lelsonar.reconstruct.estimate.record import ProvisionalState
from lelsonar.reconstruct.estimate.wire import PlaneMessages


@dataclass
class RecoveryState:
    """Requests made to the acquirer's log for one scan."""

    attempts: int = 0  # since the last progress
    last_at: float | None = None  # clock of the last request
    mark: int = -1  # steps held at the last request (more now = progress)
    requests: int = 0  # in all


@dataclass
class Partial(ProvisionalState):
    """The state of one scan in progress: the provisional estimate's, and the stream's."""

    #: Clock of the last provisional estimate, or of the scan's first message: deferred refits are caught up
    #: oldest first, and one whose scan has waited over twice ``max_provisional_delay`` is shed under a backlog.
    estimated_at: float = 0.0
    #: A provisional refit waited for a backlog (tick() catches up).
    deferred: bool = False
    last_activity: float = 0.0
    #: ns: the least (wall clock at handling − acquisition time) over the scan's live samples: their transit
    #: and the two clocks' offset; what a sample waited beyond it is its delay (None: no live sample yet).
    transit_floor_ns: int | None = None
    #: Steps held when a stale provisional estimate was last counted (one is counted a ``refit_every`` steps).
    stale_at: int = 0
    ended_at: float | None = None
    recovery: RecoveryState = field(default_factory=RecoveryState)
    #: Conflicting steps last asked of the acquirer's log, and when (its copy decides which is right).
    settling: frozenset = frozenset()
    settle_at: float | None = None
    #: The messages of the planes its provisional estimates carried (plane a's is made once).
    plane_messages: PlaneMessages = field(default_factory=PlaneMessages)
