"""``python -m clothball.game.cli``: the ``clothball`` command."""

import sys

from . import main

sys.exit(main())
