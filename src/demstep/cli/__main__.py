"""``python -m demstep.cli``: the ``demstep`` command."""

import sys

from demstep.cli import main

sys.exit(main())
