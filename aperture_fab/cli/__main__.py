"""`python -m aperture_fab.cli`: the `aperture-fab` command where it is not installed."""

import sys

from aperture_fab.cli.main import main

sys.exit(main())
