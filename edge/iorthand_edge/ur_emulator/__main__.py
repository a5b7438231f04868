"""``python -m iorthand_edge.ur_emulator``."""

import sys

from .cli import main

sys.exit(main())
