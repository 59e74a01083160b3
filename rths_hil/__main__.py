"""``python -m rths_hil`` is the same as ``rths-hil``."""

import sys

from .cli import main

sys.exit(main())
