"""lelsonar: robust plane estimates from a rotating ultrasonic array.

This package is the wire contract shared by both services: the generated
protobuf messages (:mod:`lelsonar.v1`), the key expressions, the codecs, the
frames, the error tree, and the Zenoh and MCAP plumbing.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lelsonar")
except PackageNotFoundError:  # running from a tree that was never installed
    __version__ = "0+unknown"

#: Version of the wire contract carried by every top-level message.
SCHEMA_VERSION = 1
