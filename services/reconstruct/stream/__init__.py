"""Samples in, estimates out: ingest (one decode), the per-scan assembly, the service, live and recorded
sources, recovery from the acquirers' logs, and the reconstructor group."""
