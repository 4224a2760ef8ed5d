"""What both services compute from a waveform: the echo energy and its model (eq. 10–12), echo timing,
and the compiler of the hot numeric loops (:mod:`.compiled`)."""
