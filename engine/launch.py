"""The ``packetrt`` command's entry point: numba's environment checked before numba loads.

``engine.cli`` imports the kernels, and with them numba, which reads its environment variables
at that import; a bad one was numba's traceback before ``main`` could run. This module imports
nothing that imports numba until the variables are known to be good.
"""
from __future__ import annotations

import sys

from engine.core.numba_settings import settings_problem


def main(argv=None) -> int:
    problem = settings_problem()
    if problem:
        print(f"packetrt: error: {problem}", file=sys.stderr)
        return 2
    from engine.cli import main as cli_main

    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main())
