"""``python -m segmitsuba.cli ...``: the same command line as ``python -m segmitsuba``."""

import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
