"""The log, the truth of what was acquired: MCAP recordings written durably (:mod:`.recording`), read
whatever happened to them (:mod:`.reader`), made whole again (:mod:`.recover`, ``lelsonar recover``) and
summarised (:mod:`.summary`, ``lelsonar info``)."""
