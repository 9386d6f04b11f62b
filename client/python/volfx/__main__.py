"""``python3 -m volfx ...``: the command-line client, like the C ``volfx`` CLI."""

import sys

from volfx import main

sys.exit(main())
