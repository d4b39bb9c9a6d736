"""`silcr` command lines for child processes: the sweep's cells, the benchmarks' runs, the tests.

Below the CLI, so that whatever starts a `silcr` child (the sweep, the benchmarks, the Python
API) does not import the command line itself.
"""

from __future__ import annotations

import sys
from typing import Any

from silcr.common.config import option_name


def command(*args: str) -> list[str]:
    """The command line that runs `silcr ARGS` in a child process with this interpreter.

    Not `python -m silcr.cli`: that puts the working directory first on sys.path, and from a
    source checkout with a non-editable install it finds the checkout's `silcr/` folder (the
    CLI alone, without silcr.common) instead of the installed package."""
    return [sys.executable, "-c", "import sys; sys.path.pop(0); from silcr.cli import main; sys.exit(main())", *args]


def option_args(options: dict[str, Any]) -> list[str]:
    """Options by their Config names ({"total_steps": 30000, "hidden": [64, 64], "resume": True}) as
    command-line arguments (`--total-steps 30000 --hidden 64 64 --resume`), in name order; a false
    flag is left out."""
    out: list[str] = []
    for name, value in sorted(options.items()):
        flag = option_name(name)
        if isinstance(value, bool):
            out += [flag] if value else []
        elif isinstance(value, (list, tuple)):
            out += [flag, *map(str, value)]
        else:
            out += [flag, str(value)]
    return out
