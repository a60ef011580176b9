"""``python -m device.cli``: the ``lightprobe`` command."""

import sys

from device.cli import main

sys.exit(main())
