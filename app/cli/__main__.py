"""``python -m app.cli``: what the ``trifuse`` console script runs."""

import sys

from app.cli import main

sys.exit(main())
