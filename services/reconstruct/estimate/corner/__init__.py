"""The L-corner's joint model: two walls and their edge fitted together (:mod:`.model`), and the method of
record built on it (:mod:`.method`)."""
