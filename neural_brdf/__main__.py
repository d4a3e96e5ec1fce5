"""``python -m neural_brdf ...`` is the ``neural-brdf`` command."""

import sys

from .cli import main

sys.exit(main())
