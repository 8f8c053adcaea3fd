"""The ``preston`` console script of the wheel: the command line of the ``preston`` binary (the
same Rust code, ``preston_cli::run_from_args``), run in this process, with its exit codes (0 ok,
2 bad input, 3 not converged)."""

import signal
import sys

from . import _preston


def main() -> None:
    # Ctrl-C ends the command as it ends the binary. The interpreter's own handler only sets a
    # flag, and nothing reads it while the command runs.
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    sys.exit(_preston.run_cli(["preston", *sys.argv[1:]]))


if __name__ == "__main__":
    main()
