"""``python -m independent_ur_peer``: run the peer (see the package's docstring)."""

import sys

from .server import main

sys.exit(main())
