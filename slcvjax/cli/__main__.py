"""``python -m slcvjax.cli``."""

import sys

from . import main

sys.exit(main())
