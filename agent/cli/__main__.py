"""``python -m agent.cli``: the ``uma`` command without the console script."""

import sys

from agent.cli.main import main

sys.exit(main())
