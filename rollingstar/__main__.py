"""``python -m rollingstar``: the command line."""
import sys

from rollingstar.cli import main

sys.exit(main())
