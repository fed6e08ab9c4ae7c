"""``python -m wiggly``: the command line (see :mod:`wiggly.cli`)."""

import sys

from wiggly.cli import main

if __name__ == "__main__":
    sys.exit(main())
