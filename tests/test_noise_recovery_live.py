"""Live over hermetic Zenoh equals a replay of the log, for a board that fires on noise (design notes §8).

The echoes after the noise's crossings are recovered from the waveforms: each sample's window around its
candidate echo is kept as it is placed (whatever order the samples come in: live, some of them recovered
from the acquirer's log after the rest), the decision taken at the final over the whole scan.  The live final
must be the replay's, and name the recovery.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate import wire

from . import foreign_scenes as fs
from .live_rig import Rig, renamed
from .test_live_delivery import accounting, estimate_only, replayed_final
from .test_reconstruct_foreign import NOISY_BOARD


def test_a_noise_triggered_scan_live_with_steps_recovered_from_the_log_equals_its_replay(zenoh_socket):
    scan = fs.simulate(replace(NOISY_BOARD, noise=0.0125, steps=90))
    messages = renamed(fs.messages(scan, fs.Conventions(energy_model=False)), "rig")
    steps = scan.rig.steps
    rng = np.random.default_rng(23)
    dropped = set(int(s) for s in rng.choice(steps, size=15, replace=False)) | {0, steps - 1}
    with Rig(zenoh_socket) as rig:
        service = rig.start_reconstructor()
        rig.acquirer("rig").send(messages, unpublished=dropped)
        assert rig.done.wait(60), f"no terminal estimate; stats {service.stats_dict()}"
    (final,) = rig.terminal
    assert wire.status_name(final) == "final" and list(final.missing_steps) == []
    assert accounting(final) == (steps, steps - len(dropped), len(dropped), 0, {}, 0)
    assert final.surfaces  # every surface of the sweep, as the replay's
    assert estimate_only(final) == estimate_only(replayed_final(messages))
    named = "re-timed from the first echo over the noise after it"
    assert final.planes and all(any(named in r for r in p.quality_reasons) for p in final.planes)
