"""Reading recordings whatever happened to them: the tolerant reader, ``recover`` and ``info``.

* :mod:`~lelsonar.recordings.reader` — salvage every intact message of an MCAP
  file, finished or not, and account for what was lost (generic MCAP);
* :mod:`~lelsonar.recordings.recover` — write what was salvaged as a valid,
  indexed MCAP (``lelsonar recover``);
* :mod:`~lelsonar.recordings.summary` — what a lelsonar recording holds
  (``lelsonar info``).

Writing, and the lelsonar-level reading API (``open_recording``,
``iter_payloads``, ``read_messages``), stay in :mod:`lelsonar.recording`.
"""

from lelsonar.recordings.reader import Damage, RawMessage, Salvage, salvage

__all__ = ["Damage", "RawMessage", "Salvage", "salvage"]
