"""``python -m timedexec.twins gyro [options]``: run a protocol twin in this process.

Today: ``gyro`` (a simulated MPU-6000 on a pseudo-terminal; ``gyro --help`` lists its
options). The UR and KUKA controllers run with ``timedexec serve --robot ROBOT``.
"""

from __future__ import annotations

import sys

from timedexec.twins._gyro import main as gyro_main

_TWINS = {"gyro": gyro_main}


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] not in _TWINS:
        print(
            "usage: python -m timedexec.twins gyro [--help | options]\n"
            "(UR and KUKA controllers: timedexec serve --robot ROBOT)",
            file=sys.stderr,
        )
        return 2
    return _TWINS[args[0]](args[1:])


if __name__ == "__main__":
    sys.exit(main())
