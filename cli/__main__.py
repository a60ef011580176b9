"""``python -m lightprobe.cli``: the ``lightprobe`` command."""

import sys

from lightprobe.cli import main

sys.exit(main())
