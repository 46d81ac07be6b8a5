"""``python -m trifuse.app.cli``: what the ``trifuse`` console script runs."""

import sys

from trifuse.app.cli import main

sys.exit(main())
