"""``python -m crossline.cli``: the ``crossline`` command."""

import sys

from crossline.cli import main

sys.exit(main())
