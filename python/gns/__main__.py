"""`python -m gns` is the `gns` command."""

import sys

from gns.cli import main

sys.exit(main())
