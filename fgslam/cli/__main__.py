"""``python -m fgslam.cli``: the ``fgslam`` command."""

import sys

from fgslam.cli import main

sys.exit(main())
