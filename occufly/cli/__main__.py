"""``python -m occufly.cli`` runs the ``occufly`` command line."""

import sys

from occufly.cli import main

sys.exit(main())
