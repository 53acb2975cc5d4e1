"""``python -m torchpvs`` = the ``torchpvs`` command (see :mod:`torchpvs.cli`)."""

import sys

from .cli import main

sys.exit(main())
