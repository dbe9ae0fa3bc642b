"""``python -m timedexec.cli``: the ``timedexec`` command."""

from __future__ import annotations

import sys

from timedexec.cli import main

sys.exit(main())
