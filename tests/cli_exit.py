"""A command's exit code in a test, whether its main() returns it or argparse refuses the arguments itself
(SystemExit with the code, exit 2 for a usage error: ev3dgs.cli.common._Parser)."""
from __future__ import annotations


def exit_code(main, argv) -> int:
    """``main(argv)``'s return value, or the code of the SystemExit it raised."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code
