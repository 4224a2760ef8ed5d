"""From samples to planes: :mod:`.estimate` (split, correct, LEL, LS, the baselines, the corner model) and
:mod:`.stream` (ingest, assembly, the service, sources, recovery, the group)."""
