"""``python3 -m volfx ...``: a small command line over the Python client (the C ``volfx``
is the full one; see ``volfx.main``)."""

import sys

from volfx import main

sys.exit(main())
