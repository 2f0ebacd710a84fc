"""``python -m canergy``."""

import sys

from canergy.cli import main

sys.exit(main())
