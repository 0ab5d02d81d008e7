"""`python -m gns.cli` is the `gns` command, as `python -m gns` is."""

import sys

from gns.cli import main

sys.exit(main())
