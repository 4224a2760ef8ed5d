"""lelsonar: robust plane estimates from a rotating ultrasonic array.

This package is the wire contract shared by every part: the generated protobuf
messages (:mod:`lelsonar.v1`), the key expressions, the codec, the frames, the
energy model a scan announces, and the error tree.  The rest of the system lives
in its subpackages, one folder each under ``services/`` (``services/X`` is
``lelsonar.X``).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("lelsonar")
except PackageNotFoundError:  # running from a tree that was never installed
    __version__ = "0+unknown"

#: Version of the wire contract carried by every top-level message.
SCHEMA_VERSION = 1
