"""``python -m sim.cli ...``: the same as the ``bess-ded`` console script."""

import sys

from . import main

sys.exit(main())
