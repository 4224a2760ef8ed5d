"""What every viewer draws, shared by the log and the viewers: the palette of methods and verdicts
(:mod:`.palette`) and the Foxglove scene of a scan (:mod:`.visual`: frames, beams, points, planes)."""
