"""``python -m cparticles``: the same as the ``cparticles`` console script."""

import sys

from cparticles.cli import main

if __name__ == "__main__":
    sys.exit(main())
