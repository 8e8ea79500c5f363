"""`python -m estimator.cli`: the physfuse command."""

import sys

from estimator.cli import main

sys.exit(main())
