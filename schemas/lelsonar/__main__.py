"""``python -m lelsonar``: the command line (:mod:`lelsonar.cli.main`)."""

import sys

from lelsonar.cli.main import main

sys.exit(main())
