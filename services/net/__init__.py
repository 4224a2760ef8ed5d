"""The network: Zenoh sessions and their configuration (:mod:`.transport`), mutual TLS and access control
(:mod:`.secure`)."""
