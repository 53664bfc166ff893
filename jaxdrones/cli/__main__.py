"""``python -m jaxdrones.cli ...``: the ``jaxdrones`` command."""

import sys

from jaxdrones.cli import main

sys.exit(main())
