"""`python -m kinetix` runs the command line."""

import sys

from kinetix.cli import main

sys.exit(main())
