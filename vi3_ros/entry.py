"""The ``vi3`` console script's entry point. Its first lines, before anything else of the program loads, make SIGINT
and SIGTERM end the process with status 128 + their number and one line on stderr: the imports that follow (the
command line's modules, numpy) take tens of milliseconds, and a Ctrl-C there printed Python's KeyboardInterrupt
traceback. ``vi3_ros.interrupts.exit_on_signal`` takes over once it is loaded (``vi3_ros.cli.program``).
Only the interpreter's own start, before this module runs, is not covered."""

import os
import signal


def _before_start(signum: int, frame: object) -> None:
    os.write(2, f"vi3: interrupted by {signal.Signals(signum).name} before the command started; nothing was "
                "written\n".encode())
    os._exit(128 + signum)


signal.signal(signal.SIGTERM, _before_start)
if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:  # ignored under nohup: stays so
    signal.signal(signal.SIGINT, _before_start)


def program() -> None:
    """The ``vi3`` program (``vi3_ros.cli.program``)."""
    from vi3_ros.cli import program as run

    run()
