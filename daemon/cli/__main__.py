"""``python -m wristscan.daemon.cli``: the same as the ``wristscan`` console script."""

import sys

from wristscan.daemon.cli.app import main

sys.exit(main())
