"""``python -m neural_brdf ...`` is the ``neural-brdf`` command."""

import sys

from neural_brdf.tooling.cli import main

sys.exit(main())
