"""Command-line entry points (`python -m experiments.<name>`), thin layers over `hte_jax`."""

import sys

if sys.argv[:1] == ["-m"]:  # set while `python -m experiments.<name>` is being located, i.e. imported
    import os
    import signal

    def _interrupted_while_starting(signum, frame):
        """Ctrl-C before the command's `cli.interruptible` takes over: one line, no traceback."""
        os.write(2, b"interrupted: nothing written\n")
        os._exit(130)

    signal.signal(signal.SIGINT, _interrupted_while_starting)
