"""``python -m segmitsuba ...``: the same command line as the ``segmitsuba`` console script."""

import sys

from segmitsuba.cli import main

if __name__ == "__main__":
    sys.exit(main())
